"""Every bad input of the command line gets one line on stderr, exit code 2, no traceback, and changes no file.

One table: each row sets up what it needs in a fresh folder, runs one command, and names the
fragments its error must contain. Files outside the run directory the command was given must be
exactly as they were (contents and modification times), so a refused command loses nothing.
"""

import io
import json
import os
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest
import torch

from rat.cli import main
from rat.victims.zoo import ZOO_DIR


@pytest.fixture(scope="module")
def agent_zip(tmp_path_factory) -> Path:
    """A user's own Stable-Baselines3 SAC agent for drawer-open-v3 (untrained: only its file matters here)."""
    from stable_baselines3 import SAC

    from rat.envs import make_task

    path = tmp_path_factory.mktemp("agent") / "agent.zip"
    SAC("MlpPolicy", make_task("drawer-open-v3"), learning_starts=0, buffer_size=100, seed=0).save(path)
    return path


def hostile_zip(path: Path, agent_zip: Path, *, data=None, policy: bytes | None = None) -> str:
    """``agent_zip`` with its ``data`` or ``policy.pth`` entry replaced."""
    with zipfile.ZipFile(agent_zip) as src, zipfile.ZipFile(path, "w") as out:
        for item in src.infolist():
            content = src.read(item.filename)
            if item.filename == "data" and data is not None:
                content = json.dumps(data).encode()
            if item.filename == "policy.pth" and policy is not None:
                content = policy
            out.writestr(item, content)
    return str(path)


class RunsCode:
    """Unpickling this object would call os.system: what a hostile model file could do."""

    def __reduce__(self):
        return os.system, ("touch pwned",)


def torch_bytes(obj) -> bytes:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return buffer.getvalue()


def snapshot(*roots: Path) -> dict[str, tuple[int, int]]:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for root in roots if root.exists()
            for p in sorted(root.rglob("*")) if p.is_file()}


# Each case: (id, setup(tmp, agent_zip) -> argv, fragments of the one-line error).
CASES = [
    ("web options without the web labeller", lambda t, z: ["attack", "train", "--web-port", "9000", "--out",
                                                            str(t / "run")],
     ["apply to --labeller web; add it"]),
    ("web fallback without a timeout", lambda t, z: ["intention", "train", "--labeller", "web", "--web-fallback",
                                                     "--out", str(t / "run")],
     ["--web-fallback answers after a timeout", "--web-timeout"]),
    ("web labeller for an attack that asks nothing", lambda t, z: ["attack", "train", "--method", "random",
                                                                   "--labeller", "web", "--out", str(t / "run")],
     ["asks no preference queries", "drop --labeller"]),
    ("labelling page for a missing store", lambda t, z: ["labels", "serve", str(t / "nothing.sqlite")],
     ["no label store at"]),
    ("locomotion SAC run too short", lambda t, z: ["victim", "train", "--task", "HalfCheetah-v5", "--method", "sac",
                                                   "--total-steps", "100", "--out", str(t / "run")],
     ["end before SAC's first update", "--total-steps > 5000"]),
    ("locomotion victim by behaviour cloning", lambda t, z: ["victim", "train", "--task", "Walker2d-v5",
                                                             "--out", str(t / "run")],
     ["Walker2d-v5 has no scripted expert", "--method sac"]),
    ("Decision Transformer without data", lambda t, z: ["victim", "dt", "--out", str(t / "run")],
     ["--expert", "--data", "one of the two"]),
    ("unknown task", lambda t, z: ["victim", "eval", "zoo:drawer-open-v3", "--task", "drawer-opne-v3"],
     ["unknown task 'drawer-opne-v3'", "did you mean 'drawer-open-v3'"]),
    ("foreign victim without its task", lambda t, z: ["attack", "train", "--method", "random", "--victim", str(z),
                                                      "--out", str(t / "run")],
     ["does not record its task", "pass --task"]),
    ("negative budget", lambda t, z: ["attack", "train", "--budget", "-5", "--out", str(t / "run")],
     ["budget must not be negative"]),
    ("epsilon zero", lambda t, z: ["attack", "train", "--method", "random", "--epsilon", "0", "--out", str(t / "run")],
     ["epsilon 0 allows no perturbation", "--epsilon > 0"]),
    ("SAC updates per step not a number", lambda t, z: ["attack", "train", "--set", "pebble.updates_per_step=nan",
                                                         "--out", str(t / "run")],
     ["updates-per-step must be a finite number >= 0, got nan"]),
    ("negative epsilon", lambda t, z: ["attack", "train", "--epsilon", "-1", "--out", str(t / "run")],
     ["epsilon must be a finite number >= 0"]),
    ("RAT run too short", lambda t, z: ["attack", "train", "--steps", "5000", "--out", str(t / "run")],
     ["first labels come at step 10000", "--steps > 10000", "--preset smoke"]),
    ("RAT warm-up longer than the run", lambda t, z: ["attack", "train", "--preset", "smoke", "--pretrain-steps",
                                                      "5000", "--out", str(t / "run")],
     ["first labels come at step 5500"]),
    ("PPO run too short", lambda t, z: ["attack", "train", "--method", "sa-rl", "--reward", "oracle", "--steps", "100",
                                        "--out", str(t / "run")], ["PPO's first update", "--steps >= 2048"]),
    ("intention run too short", lambda t, z: ["intention", "train", "--steps", "500", "--out", str(t / "run")],
     ["first labels come at step 10000"]),
    ("warm-up on an attack without one", lambda t, z: ["attack", "train", "--method", "random", "--seed-steps", "10",
                                                       "--out", str(t / "run")], ["do not apply to attack 'random'"]),
    ("a path that does not exist", lambda t, z: ["victim", "ship", str(t / "nothing"), "door-lock-v3@sac"],
     ["'SOURCE'", "does not exist", "see 'rat victim ship --help'"]),
    ("an option no command has", lambda t, z: ["attack", "train", "--epsilom", "0.1", "--out", str(t / "run")],
     ["No such option '--epsilom'", "--epsilon", "see 'rat attack train --help'"]),
    ("a command that does not exist", lambda t, z: ["atack", "train"], ["No such command 'atack'"]),
    ("out is a file", lambda t, z: (t / "file").write_text("mine") and
     ["attack", "train", "--method", "random", "--out", str(t / "file")], ["is a file, not a folder"]),
    ("out under a file", lambda t, z: (t / "file").write_text("mine") and
     ["attack", "train", "--method", "random", "--out", str(t / "file" / "run")], ["lies under a file"]),
    ("out not writable", lambda t, z: ["attack", "train", "--method", "random", "--out", "/proc/rat-run"],
     ["cannot write in --out"]),
    ("out is someone else's folder", lambda t, z: (t / "mine").mkdir() or (t / "mine" / "report.json").write_text("{}")
     and ["attack", "train", "--method", "random", "--out", str(t / "mine")], ["is not a rat run", "no config.json"]),
    ("a report of a grid that would adopt a run", lambda t, z: ["bench", "table1", "--report-only", "--adopt",
                                                                str(t / "mine"), "--out", str(t / "grid")],
     ["--report-only runs nothing", "give one or the other"]),
    ("video not writable", lambda t, z: ["victim", "eval", "zoo:drawer-open-v3", "--video", "/proc/rat/v.mp4"],
     ["cannot write in the folder of --video"]),
    ("video is a folder", lambda t, z: ["victim", "eval", "zoo:drawer-open-v3", "--video", str(t)],
     ["--video", "is a folder"]),
    ("pickle with code in a model file", lambda t, z: [
        "victim", "eval", hostile_zip(t / "evil.zip", z, policy=torch_bytes({"w": RunsCode()})), "--task",
        "drawer-open-v3"], ["holds Python objects besides tensors", "never loads"]),
    ("model data that is a list", lambda t, z: ["victim", "eval", hostile_zip(t / "list.zip", z, data=[1, 2]),
                                                "--task", "drawer-open-v3"], ["is a JSON list"]),
    ("model weights that are a bare tensor", lambda t, z: [
        "victim", "eval", hostile_zip(t / "bare.zip", z, policy=torch_bytes(torch.zeros(3))), "--task",
        "drawer-open-v3"], ["not a state dict of named tensors", "Tensor"]),
    ("labels list on an empty file", lambda t, z: (t / "empty.sqlite").write_bytes(b"") or
     ["labels", "list", str(t / "empty.sqlite")], ["is not a rat label store"]),
    ("labels list on another database", lambda t, z: other_database(t / "other.sqlite") and
     ["labels", "list", str(t / "other.sqlite")], ["is not a rat label store"]),
    ("labels import from nowhere", lambda t, z: ["labels", "import", str(t / "new.sqlite"), str(t / "missing.sqlite")],
     ["no label store at"]),
    ("adversary.json without its victim", lambda t, z: edited_run(t, victim=None) and
     ["attack", "eval", str(t / "edited"), "--episodes", "1"], ["does not record its victim", "edited"]),
    ("adversary.json without its target", lambda t, z: edited_run(t, target=None) and
     ["attack", "eval", str(t / "edited"), "--episodes", "1"], ["lacks target", "edited, or not written by rat"]),
    ("unknown plugin", lambda t, z: ["--plugin", "not_a_module_anywhere", "list", "attacks"], ["cannot be imported"]),
    ("unknown attack", lambda t, z: ["attack", "train", "--method", "fgsm", "--out", str(t / "run")],
     ["unknown attack 'fgsm'", "rat list attacks"]),
    ("no GPU", lambda t, z: ["intention", "train", "--device", "cuda", "--out", str(t / "run")]
     if not torch.cuda.is_available() else ["intention", "train", "--device", "tpu"], ["GPU"]),
]


def other_database(path: Path) -> bool:
    import sqlite3

    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE notes (text TEXT)")
        db.execute("INSERT INTO notes VALUES ('keep me')")
    db.close()
    return True


def edited_run(tmp: Path, **changes) -> bool:
    """A run whose adversary.json was edited by hand: ``changes`` set to None are removed."""
    meta = {"victim": "zoo:drawer-open-v3", "task": "drawer-open-v3", "target": "reach", "method": "random",
            "epsilon": 0.1, "norm": "linf", "seed": 0, "obs_dim": 39}
    meta = {k: v for k, v in {**meta, **changes}.items() if v is not None}
    run = tmp / "edited"
    run.mkdir()
    (run / "adversary.json").write_text(json.dumps({"format": "rat-checkpoint", "version": 1, "kind": "adversary",
                                                    "meta": meta}))
    (run / "adversary.safetensors").write_bytes(b"")
    return True


@pytest.mark.parametrize("name, make_argv, fragments", CASES, ids=[c[0] for c in CASES])
def test_a_bad_input_is_one_line_and_changes_nothing(name, make_argv, fragments, tmp_path, agent_zip, capsys):
    argv = make_argv(tmp_path, agent_zip)
    before = snapshot(tmp_path, ZOO_DIR, Path(os.environ["RAT_ZOO"]), agent_zip.parent)
    code = main(argv)
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert code == 2, (out, err)
    assert len(lines) == 1 and lines[0].startswith("rat: error: ") and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    after = snapshot(tmp_path, ZOO_DIR, Path(os.environ["RAT_ZOO"]), agent_zip.parent)
    assert before == after, {p for p in set(before) | set(after) if before.get(p) != after.get(p)}
    assert not (tmp_path / "run").exists()  # a refused run leaves no directory behind
    assert not Path("pwned").exists()


def test_a_users_sb3_agent_is_attacked_from_the_cli_given_its_task(agent_zip, tmp_path, capsys):
    code = main(["attack", "train", "--method", "random", "--victim", str(agent_zip), "--task", "drawer-open-v3",
                 "--set", "final_eval_episodes=1", "--no-video", "--out", str(tmp_path / "run")])
    out, err = capsys.readouterr()
    assert code == 0 and "random (none) attack success" in out, err
    code = main(["attack", "eval", str(tmp_path / "run"), "--episodes", "1", "--record", str(tmp_path / "sizes.csv")])
    out, err = capsys.readouterr()
    assert code == 0, err
    rows = (tmp_path / "sizes.csv").read_text().splitlines()
    assert rows[0] == "episode,step,norm,epsilon,within_budget" and len(rows) == 1 + 501  # reset + 500 steps
    assert all(row.endswith(",1") for row in rows[1:])


def test_a_run_directory_in_use_by_another_process_is_refused_naming_it(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import sys, time
        from rat.runs import claim_run_dir
        from pathlib import Path
        claim_run_dir(Path({str(run)!r}))
        print("held", flush=True)
        time.sleep(60)
    """)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        code = main(["attack", "train", "--method", "random", "--out", str(run)])
        err = capsys.readouterr().err
        assert code == 2 and f"process {holder.pid}" in err and "is in use by" in err, err
    finally:
        holder.kill()
        holder.wait()
    from rat.runs import claim_run_dir

    claim_run_dir(run)  # the holder is gone: its lock went with it


def test_a_run_whose_configuration_is_damaged_is_refused_in_one_line_and_kept(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text('{"rat": {"pebb')
    assert main(["attack", "train", "--method", "random", "--out", str(run)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "config.json' is corrupted (JSONDecodeError)" in err, err
    assert "restore it from a copy" in err and (run / "config.json").read_text() == '{"rat": {"pebb'


def test_a_resume_with_other_settings_names_each_one_and_both_values(tmp_path, capsys):
    args = ["attack", "train", "--method", "random", "--no-video", "--set", "final_eval_episodes=1",
            "--out", str(tmp_path / "run")]
    assert main(args) == 0
    capsys.readouterr()
    assert main(args[:-2] + ["--epsilon", "0.2"] + args[-2:]) == 2
    err = capsys.readouterr().err
    assert "epsilon = 0.1 in the run, 0.2 now" in err and err.count("\n") == 1, err
