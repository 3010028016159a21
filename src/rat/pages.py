"""One static HTML page of a run or a grid (``rat report FOLDER``): what a person would rather see than read.

- A **run** (an attack, a robust agent, a victim: a folder with ``report.json``): its summary, the training plot,
  the attacked-episode video, a robust agent's table of fresh attacks, and its settings.
- A **table-1 grid** (``results.csv`` + ``table1.md``): the table with the paper's numbers beside ours, the
  success curves and the videos kept beside it.
- A **table-3 grid** (rows ``<task>/<row>-seed<k>/row.json``): its table, and each row's training plot.
- An **audit** (``audit.json``, :mod:`rat.experiments.audit`): success and return against ε per attack, the table
  with intervals and perturbation sizes, the attacked-episode videos, what did not run and why.

The page sits in the folder and names its images and videos relatively, so the folder can be moved or served
as it is. Nothing is fetched from elsewhere.
"""

from __future__ import annotations

import html
import json
import re
from pathlib import Path
from typing import Any

from rat.errors import RatError

STYLE = """
body { font-family: system-ui, sans-serif; max-width: 72rem; margin: 2rem auto; padding: 0 1rem; color: #222; }
h1 { font-size: 1.5rem; } h2 { font-size: 1.2rem; margin-top: 2rem; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; font-size: 0.85rem; } td, th { border: 1px solid #ccc; padding: 0.25rem 0.5rem; }
th { background: #f4f4f4; } td.num { text-align: right; } img, video { max-width: 100%; }
dl { display: grid; grid-template-columns: max-content auto; gap: 0.2rem 1rem; } dt { font-weight: 600; }
pre { background: #f7f7f7; padding: 0.5rem; overflow-x: auto; font-size: 0.8rem; }
"""


NUMERIC = re.compile(r"^[*(\d–-]")  #: a cell that starts like a number (right-aligned)


def _inline(text: str) -> str:
    """Markdown's inline marks this project's tables use: **bold**, `code`, [links](target)."""
    out = html.escape(text)
    out = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", out)
    out = re.sub(r"`(.+?)`", r"<code>\1</code>", out)
    return re.sub(r"\[([^\]]+)\]\(([^)\s]+)\)", r'<a href="\2">\1</a>', out)


def markdown_to_html(text: str) -> str:
    """The markdown of this project's generated tables: headings, paragraphs and pipe tables."""
    parts, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("|"):
            rows = []
            while i < len(lines) and lines[i].startswith("|"):
                rows.append([c.strip() for c in lines[i].strip().strip("|").split("|")])
                i += 1
            head, body = rows[0], [r for r in rows[1:] if not all(set(c) <= set("-: ") for c in r)]
            cells = "".join(f"<th>{_inline(c)}</th>" for c in head)
            parts.append(f"<table><thead><tr>{cells}</tr></thead><tbody>")
            for r in body:
                parts.append("<tr>" + "".join(f"<td{' class=num' * bool(NUMERIC.match(c))}>{_inline(c)}</td>"
                                              for c in r) + "</tr>")
            parts.append("</tbody></table>")
            continue
        if line.startswith("#"):
            level = min(len(line) - len(line.lstrip("#")) + 1, 4)
            parts.append(f"<h{level}>{_inline(line.lstrip('#').strip())}</h{level}>")
        elif line.strip():
            parts.append(f"<p>{_inline(line)}</p>")
        i += 1
    return "\n".join(parts)


def _section(title: str, body: str) -> str:
    return f'<section id="{re.sub(r"[^a-z0-9]+", "-", title.lower()).strip("-")}"><h2>{html.escape(title)}</h2>\n{body}\n</section>'


def _media(folder: Path, names: list[str]) -> str:
    out = []
    for name in names:
        if name.endswith(".mp4"):
            out.append(f'<figure><video src="{html.escape(name)}" controls muted loop preload="metadata"></video>'
                       f"<figcaption>{html.escape(name)}</figcaption></figure>")
        else:
            out.append(f'<figure><img src="{html.escape(name)}" alt="{html.escape(name)}">'
                       f"<figcaption>{html.escape(name)}</figcaption></figure>")
    return "\n".join(out)


def _facts(report: dict[str, Any]) -> str:
    """The report's scalar facts as a definition list, rates in percent."""
    items = []
    for key, value in report.items():
        if isinstance(value, (dict, list)) and key != "attack_success_ci":
            continue
        if key == "attack_success_ci":
            value = f"{100 * value[0]:.1f}–{100 * value[1]:.1f}%"
        elif isinstance(value, float) and ("rate" in key or "success" in key):
            value = f"{100 * value:.1f}%"
        elif isinstance(value, float):
            value = f"{value:.4g}"
        items.append(f"<dt>{html.escape(key.replace('_', ' '))}</dt><dd>{html.escape(str(value))}</dd>")
    return "<dl>" + "".join(items) + "</dl>"


def _robust_table(table: dict) -> str:
    rows = "".join(f"<tr><td>{html.escape(name)}</td><td>{html.escape(row['reward'])}</td>"
                   f"<td class=num>{row['return']:.1f} ± {row['return_std']:.1f}</td>"
                   f"<td class=num>{100 * row['target_success']:.1f}%</td><td class=num>{row['episodes']}</td></tr>"
                   for name, row in table["attacks"].items())
    return (f"<p>Clean return {table['clean_return']:.1f} ± {table['clean_return_std']:.1f}.</p><table><thead><tr>"
            "<th>attack</th><th>reward</th><th>task return</th><th>target reached</th><th>episodes</th></tr></thead>"
            f"<tbody>{rows}</tbody></table>")


def _page(title: str, sections: list[str]) -> str:
    return (f"<!doctype html>\n<html lang=en><head><meta charset=utf-8><title>{html.escape(title)}</title>"
            f"<style>{STYLE}</style></head><body>\n<h1>{html.escape(title)}</h1>\n" + "\n".join(sections)
            + "\n</body></html>\n")


def run_page(folder: Path) -> str:
    report = json.loads((folder / "report.json").read_text())
    what = report.get("method", "run")
    title = f"{what}: {report.get('victim', '?')} towards {report.get('target', '?')}"
    sections = [_section("Summary", _facts(report))]
    plots = sorted(p.name for p in folder.glob("*.png"))
    if plots:
        sections.append(_section("Training", _media(folder, plots)))
    videos = sorted(p.name for p in folder.glob("*.mp4"))
    if videos:
        sections.append(_section("Attacked episodes", _media(folder, videos)))
    if (folder / "eval" / "table.json").exists():
        sections.append(_section("Fresh attacks", _robust_table(json.loads((folder / "eval" / "table.json").read_text()))))
    if (folder / "config.json").exists():
        config = json.dumps(json.loads((folder / "config.json").read_text()), indent=1)
        sections.append(_section("Settings", f"<details><summary>config.json</summary><pre>{html.escape(config)}"
                                             "</pre></details>"))
    return _page(title, sections)


def grid_page(folder: Path, table: str, title: str) -> str:
    sections = [_section("Table", markdown_to_html((folder / table).read_text()))]
    images = sorted(str(p.relative_to(folder)) for p in folder.glob("*.png"))
    images += sorted(str(p.relative_to(folder)) for p in folder.glob("*/*-seed*/training.png"))
    if images:
        sections.append(_section("Curves", _media(folder, images)))
    videos = sorted(p.name for p in folder.glob("*.mp4"))
    if videos:
        sections.append(_section("Attacked episodes", _media(folder, videos)))
    return _page(title, sections)


def _pct(value) -> str:
    return "–" if value is None else f"{100 * value:.1f}%"


def _num(value) -> str:
    return "–" if value is None else f"{value:.4g}"


def audit_page(folder: Path) -> str:
    """The page of a ``rat audit`` folder: success and return against ε, the table, videos, what did not run."""
    record = json.loads((folder / "audit.json").read_text())
    victim = record.get("victim", folder.name)
    done = [r for r in record["rows"] if r["status"] == "done"]
    summary = (f"<p>Victim <code>{html.escape(str(victim))}</code>; targets {html.escape(', '.join(record['targets']))};"
               f" ε {html.escape(', '.join(f'{e:g}' for e in record['epsilons']))}; {len(done)} of "
               f"{len(record['rows'])} cells measured in {record['minutes']:.1f} minutes (budget "
               f"{record['budget_minutes']:g}).</p>")
    head = ("<tr><th>target</th><th>ε</th><th>attack</th><th>reward</th><th>target reached (95% CI)</th>"
            "<th>clean</th><th>task return attacked</th><th>clean</th><th>max ‖Δ‖</th><th>mean ‖Δ‖</th>"
            "<th>episodes</th><th>minutes</th></tr>")
    body = "".join(
        f"<tr><td>{html.escape(r['target'])}</td><td class=num>{r['epsilon']:g}</td><td>{html.escape(r['attack'])}</td>"
        f"<td>{html.escape(r['reward'])}</td><td class=num>{_pct(r['attack_success_rate'])} "
        f"({_pct(r['ci_low'])}–{_pct(r['ci_high'])})</td><td class=num>{_pct(r['clean_success_rate'])}</td>"
        f"<td class=num>{_num(r['attacked_return'])}</td><td class=num>{_num(r['clean_return'])}</td>"
        f"<td class=num>{_num(r['max_perturbation'])}</td><td class=num>{_num(r['mean_perturbation'])}</td>"
        f"<td class=num>{r['episodes']}</td><td class=num>{_num(r['minutes'])}</td></tr>" for r in done)
    skipped = [r for r in record["rows"] if r["status"] != "done"]
    missing = "".join(f"<li>{html.escape(r['target'])}, ε = {r['epsilon']:g}, {html.escape(r['attack'])}: "
                      f"{html.escape(r['status'])} ({html.escape(r.get('why', ''))})</li>" for r in skipped)
    sections = [_section("Summary", summary), _section("Success and return against ε", _media(folder, ["audit.png"])),
                _section("Table", f"<table><thead>{head}</thead><tbody>{body}</tbody></table>"),
                _section("Not run", f"<ul>{missing}</ul>" if missing else "<p>Every cell ran.</p>")]
    videos = list(record.get("videos", {}).values())
    if videos:
        sections.insert(3, _section("Attacked episodes", _media(folder, videos)))
    return _page(f"Audit: {victim}", sections)


def write_page(folder: str | Path) -> Path:
    """Write the page of ``folder`` (a run, a table-1 grid or a table-3 grid) to ``folder/report.html``."""
    folder = Path(folder)
    if (folder / "audit.json").exists():
        text = audit_page(folder)
    elif (folder / "report.json").exists():
        text = run_page(folder)
    elif (folder / "table1.md").exists():
        text = grid_page(folder, "table1.md", f"Table 1: {folder.name}")
    elif (folder / "table3.md").exists():
        text = grid_page(folder, "table3.md", f"Table 3: {folder.name}")
    else:
        raise RatError(f"'{folder}' is neither a finished run (report.json) nor a grid (table1.md, table3.md); "
                       "give a run directory or a `rat bench` folder")
    path = folder / "report.html"
    path.write_text(text)
    return path
