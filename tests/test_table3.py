"""`rat bench table3`: the grid's driver, its caching and its table."""

import json
import re

import pytest

from rat.experiments.table3 import markdown_table3, pooled


def row(name, seed, ret, std, success, clean=(100.0, 10.0)):
    return {"task": "faucet-close-v3", "row": name, "seed": seed, "target": "reach", "epsilon": 0.1, "norm": "linf",
            "preset": "cpu", "clean_return": clean[0], "clean_return_std": clean[1],
            "attacks": {"rat": {"return": ret, "return_std": std, "target_success": success, "episodes": 100},
                        "random": {"return": 90.0, "return_std": 0.0, "target_success": 0.0, "episodes": 100}}}


def table_rows(text: str, part: int = 0) -> dict[str, str]:
    """The rows of the page's first table (``part=0``), of its tests against the undefended victim (1) or against
    the control (2)."""
    chunk = re.split("Against the undefended victim|Against the control", text)[part]
    return {line.split(" | ")[0]: line for line in chunk.splitlines() if line.startswith("| ")}


def test_pooled_is_the_mean_and_std_of_all_the_episodes():
    import numpy as np

    a, b = np.array([1.0, 3.0, 5.0]), np.array([10.0, 12.0, 20.0])
    mean, std = pooled([a.mean(), b.mean()], [a.std(), b.std()])
    assert mean == pytest.approx(np.concatenate([a, b]).mean()) and std == pytest.approx(np.concatenate([a, b]).std())


def test_the_table_puts_each_row_beside_the_papers_and_leaves_random_out_of_the_average():
    text = markdown_table3([row("undefended", 0, 10.0, 5.0, 0.9), row("rat-atla", 0, 40.0, 4.0, 0.2),
                            row("rat-atla", 1, 60.0, 4.0, 0.4)])
    lines = table_rows(text)
    assert "| undefended (zoo SAC) | 1 | 100 ± 10 | **10 ± 5** (90%) | **90 ± 0** (0%) | 10 |" in text
    atla = lines["| RAT-ATLA"]
    assert "| 2 |" in atla and "**50 ± 11** (30%) / 1048" in atla  # two seeds pooled; the paper's 1048
    assert atla.endswith("| 50 / 947 |")  # the attacks' mean without random's; the paper's avg R


def test_each_defence_is_tested_against_the_undefended_victim_under_rat():
    defended = dict(row("rat-atla", 0, 40.0, 4.0, 0.2), train_minutes=95.0)
    worse = dict(row("atla", 0, 9.0, 5.0, 0.9), train_minutes=80.0)
    text = markdown_table3([row("undefended", 0, 10.0, 5.0, 0.9), defended, worse])
    lines = table_rows(text, 1)
    rat_atla = lines["| RAT-ATLA"].split(" | ")
    assert rat_atla[3] == "20/100" and float(rat_atla[2]) < 1e-50 and float(rat_atla[4]) < 1e-20
    assert rat_atla[5] == "95 |"  # its minutes
    atla = lines["| ATLA (SAC agent)"].split(" | ")
    assert float(atla[2]) > 0.5 and float(atla[4]) > 0.4  # no better: nothing significant
    assert "Against the control" not in text  # no control row, no test against it


def test_each_defence_is_also_tested_against_the_control():
    control = dict(row("none", 0, 30.0, 5.0, 0.5), train_minutes=26.0)
    defended = dict(row("rat-atla", 0, 40.0, 4.0, 0.2), train_minutes=95.0)
    text = markdown_table3([row("undefended", 0, 10.0, 5.0, 0.9), control, defended])
    against_control = table_rows(text, 2)
    assert "| 50/100 |" in against_control["| fine-tuned, no defence"]
    rat_atla = against_control["| RAT-ATLA"].split(" | ")
    assert rat_atla[3] == "20/100" and float(rat_atla[2]) < 1e-30 and float(rat_atla[4]) < 1e-4
    assert "| fine-tuned, no defence" in table_rows(text, 1)  # the control is itself tested against the victim


@pytest.mark.slow
def test_bench_table3_attacks_the_undefended_victim_and_keeps_what_it_measured(tmp_path, capsys):
    from rat.cli import main

    def grid(jobs="1", seeds="0"):
        return ["bench", "table3", "--rows", "undefended", "--attacks", "random", "--episodes", "3", "--preset", "smoke",
                "--jobs", jobs, "--seeds", seeds, "--out", str(tmp_path)]

    args = grid()
    assert main(args) == 0
    cell = tmp_path / "faucet-close-v3" / "undefended-seed0"
    record = json.loads((cell / "row.json").read_text())
    assert record["victim"] == "zoo:faucet-close-v3@sac"  # which zoo victim the row is
    assert record["attacks"]["random"]["episodes"] == 3 and record["clean_return"] > 1000  # the zoo victim succeeds
    assert "undefended (zoo SAC)" in (tmp_path / "table3.md").read_text()
    (cell / "eval" / "random" / "table-row.json").write_text(json.dumps({**record["attacks"]["random"], "return": -1.0}))
    assert main(args) == 0  # finished cells are not measured again
    assert json.loads((cell / "row.json").read_text())["attacks"]["random"]["return"] == -1.0
    assert main(grid(jobs="2", seeds="0,1")) == 0  # two processes; seed 0's cell is kept
    assert json.loads((tmp_path / "faucet-close-v3" / "undefended-seed1" / "row.json").read_text())["seed"] == 1
    assert json.loads((cell / "row.json").read_text())["attacks"]["random"]["return"] == -1.0
    assert main(["bench", "table3", "--rows", "nobody", "--out", str(tmp_path)]) == 2
    assert "unknown table-3 rows nobody" in capsys.readouterr().err


def test_a_row_names_its_method_and_the_settings_that_differ_from_the_methods_defaults():
    from rat.experiments.table3 import ROW_SETTINGS, ROWS, row_config

    worst = row_config("rat-wocar-worst", "cpu", 3)
    assert (worst.method, worst.wocar_critic, worst.seed) == ("rat-wocar", "worst-case", 3)
    assert not worst.needs_adversary  # WocaR's estimate needs no attacker
    released = row_config("rat-wocar", "cpu", 3)
    assert (released.method, released.wocar_critic) == ("rat-wocar", "intention")
    assert set(ROW_SETTINGS) < set(ROWS)


def test_the_cli_runs_every_row_by_default():
    """The CLI writes its default out by hand (it imports nothing heavy); it must name every row."""
    from rat.cli import cli
    from rat.experiments.table3 import ROWS

    command = cli.commands["bench"].commands["table3"]
    assert next(p.default for p in command.params if p.name == "rows") == ",".join(ROWS)


def test_the_cli_offers_every_robust_method():
    from rat.cli import cli
    from rat.robust.trainer import METHODS

    command = cli.commands["robust"].commands["train"]
    assert set(next(p.type.choices for p in command.params if p.name == "method")) == set(METHODS)


def test_the_rows_start_from_the_tasks_sac_victim_from_demonstrations_first_else_the_fine_tuned_clone():
    from rat.errors import RatError
    from rat.victims.zoo import sac_victim, zoo_victims

    assert sac_victim("faucet-close-v3") == "zoo:faucet-close-v3@sac"
    fine_tuned = [t for t, kinds in zoo_victims().items() if "sac-ft" in kinds and "sac" not in kinds]
    for task in fine_tuned:
        assert sac_victim(task) == f"zoo:{task}@sac-ft"
    with pytest.raises(RatError, match="no SAC victim of window-open-v3.*rat victim ship RUN window-open-v3@sac-ft"):
        sac_victim("window-open-v3")
