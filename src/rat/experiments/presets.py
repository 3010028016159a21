"""Named budgets, as data, in one place: what ``--preset`` means for every command and the grid.

- ``paper``: the paper's settings (10⁶ environment steps per learner, batch 1024, 128 queries
  every 5,000 steps, its label counts): for a GPU machine and many hours.
- ``cpu``: what this project runs on a 2-core CPU machine: 50,000 environment steps, SAC and
  adversary batches of 256, the label budget spent in rounds every 5,000 steps from step 10,000
  to 90% of the run (8 rounds at 50,000 steps), at most 30 reward-model epochs and 400 updates per
  member per round (so a round costs about the same at 9,000 labels as at 1,700); the
  adversary imitates the intention policy kept at the last evaluation (``imitate="best"``), and the
  adversary kept at the end is the snapshot (one per evaluation) that the final r̂ scores best.
  PPO (SA-RL, PA-AD) with SB3's default learning rate and minibatch.
- ``smoke``: minutes, not results (3,000 RAT steps with 40 labels after a 1,000-step warm-up;
  one PPO rollout); for trying a command, a grid or a cluster end to end.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

from rat.attacks.rat import RATConfig
from rat.attacks.rl import PPOConfig
from rat.configs import with_values
from rat.errors import RatError
from rat.experiments.paper import PAPER_OPPOSITE_LABELS
from rat.preferences.pebble import PebbleConfig

if TYPE_CHECKING:
    from rat.experiments.table1 import Cell

PRESETS = ("cpu", "paper", "smoke")  #: presets of a single attack
SCENARIOS = ("manipulation", "opposite")  #: the reach target; every other target

#: Each preset's RAT settings as data: dotted fields of :class:`RATConfig`, for every scenario (``any``) and for
#: one. Two values are not data but a rule, applied after: the ``cpu`` and ``smoke`` presets spend the label
#: budget in equal rounds (``pebble.per_round``) from the first round until ``spend_by`` of the run.
#: ``rat list presets`` prints this table. Where each departure from the paper was measured: the comments.
RAT_PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    # The paper's settings (10⁶ environment steps per learner, batch 1024, 128 queries every 5,000 steps).
    "paper": {"any": {"total_steps": 1_000_000}},
    "cpu": {
        # Departures for a CPU: 5×10⁴ steps, SAC and adversary batches of 256; reward rounds capped (30 epochs,
        # 400 updates a member), since each round trains on every label so far (9,000 labels: 27 minutes in all
        # with the cap; docs/notes/strength-log.md). bf16 and held-out reward rounds are cheaper (benchmarks/speed.md)
        # but not the default: the main job's seed 0 made 10.0% with them, 100% without.
        # Keep the snapshot whose attack the final r̂ scores best (short PEBBLE runs are not monotone, and the
        # attacker judges its attack only through r̂), and imitate π_θ as kept at the last evaluation: the main
        # job's last adversary made 86.7 / 76.7 / 100% with it, 13.3 / 10.0 / 46.7% without (docs/notes/strength-log.md).
        "any": {"total_steps": 50_000, "adversary_batch": 256, "select": "reward", "imitate": "best",
                "pebble.sac.batch_size": 256, "pebble.reward.max_epochs": 30, "pebble.reward.max_updates": 400},
        # Measured on 3 seeds of the SAC faucet victim's row (docs/notes/strength-log.md, "Queries from recent episodes only",
        # and "Refining by l2, and by π_θ's critic where l2 falls short"): r̂'s inputs standardised, queries from
        # the last 20 episodes, the adversary imitating π_θ as it moves, the last adversary kept, Δ refined 50
        # steps by l2 and by π_θ's critic where l2 leaves a gap above 1: 100 / 96.7 / 96.7%.
        "manipulation": {"pebble.max_episodes": 20, "pebble.reward.normalize_inputs": True, "select": "last",
                         "imitate": "current", "refine_steps": 50, "refine_loss": "l2-or-q"},
    },
    # Minutes, not results: 3,000 steps, 40 labels after a 1,000-step warm-up.
    "smoke": {"any": {"total_steps": 3_000, "adversary_batch": 256, "select": "reward", "imitate": "best",
                      "pebble.sac.batch_size": 256, "pebble.reward.max_epochs": 30, "pebble.reward.max_updates": 400,
                      "pebble.budget": 40, "pebble.seed_steps": 500, "pebble.unsupervised_steps": 500,
                      "pebble.feedback_every": 1_000, "eval_every": 1_000, "eval_episodes": 1,
                      "final_eval_episodes": 2}},
}
#: The released schedule of the weighting network, every preset: manipulation vs opposite behaviours.
SCENARIO_SETTINGS = {"manipulation": {"weighting_every": 1000}, "opposite": {"weighting_every": 2000}}

# smoke: minutes, not results (the PPO and grid presets read these)
SMOKE_STEPS = {"rat": 3_000, "ppo": 2_048}
SMOKE_LABELS = 40
SMOKE_EVALUATION = {"eval_every": 1_000, "eval_episodes": 1, "final_eval_episodes": 2}


def _check_preset(preset: str) -> None:
    if preset not in PRESETS:
        raise RatError(f"unknown preset '{preset}'; use one of: {', '.join(PRESETS)}")


def scenario_of(target: str) -> str:
    return "manipulation" if target == "reach" else "opposite"


def preset_values(preset: str, target: str = "reach") -> dict[str, Any]:
    """The dotted RAT settings preset ``preset`` gives a run towards ``target`` (before the budget's rounds)."""
    _check_preset(preset)
    scenario = scenario_of(target)
    table = RAT_PRESETS[preset]
    return {**SCENARIO_SETTINGS[scenario], **table["any"], **table.get(scenario, {})}


def rat_config(preset: str = "cpu", budget: int | None = None, steps: int | None = None, target: str = "reach",
               pebble_overrides: dict | None = None, spend_by: float = 0.9, **overrides) -> RATConfig:
    """A :class:`RATConfig` from a preset (:data:`RAT_PRESETS`), a label budget (default: the preset's), overrides
    of PEBBLE's fields (the warm-up, say; applied before the budget is spread over rounds) and of any RAT field.

    The ``cpu`` and ``smoke`` presets spend the budget in equal rounds every ``feedback_every`` steps
    from the first round until ``spend_by`` of the run (the last round may be smaller).
    """
    if not 0 < spend_by <= 1:
        raise RatError(f"spend-by must lie in (0, 1], got {spend_by}")
    pebble_overrides = pebble_overrides or {}
    given = {f"pebble.{k}": v for k, v in pebble_overrides.items()}
    # a field given whole (pebble.sac=SACConfig(...)) replaces the preset's settings inside it
    values = {k: v for k, v in preset_values(preset, target).items() if not any(k.startswith(g + ".") for g in given)}
    values |= given
    if steps:
        values["total_steps"] = steps
    if budget is not None:
        values["pebble.budget"] = budget
    flat = {k: v for k, v in values.items() if not k.startswith("pebble.")}
    pebble = with_values(PebbleConfig(), {k[len("pebble."):]: v for k, v in values.items() if k.startswith("pebble.")})
    if preset != "paper":  # the budget in equal rounds, spent by `spend_by` of the run
        total = flat.get("total_steps", RATConfig.total_steps)
        first, last = pebble.warm_up, max(pebble.warm_up, int(spend_by * total))
        rounds = (last - first) // pebble.feedback_every + 1
        pebble = replace(pebble, per_round=pebble_overrides.get("per_round") or max(1, -(-pebble.budget // rounds)))
    return RATConfig(**(flat | {"pebble": pebble} | overrides))


def ppo_preset(preset: str = "cpu", steps: int | None = None, **overrides) -> PPOConfig:
    """PPO budgets by name: ``paper`` (table 6, 10⁶ steps), ``cpu`` (this machine) or ``smoke`` (one rollout)."""
    _check_preset(preset)
    if preset == "paper":
        return replace(PPOConfig(total_steps=steps or 1_000_000), **overrides)
    # Departure for a CPU: table 6's learning rate (5e-5) and minibatch (32) need ~10⁶ steps;
    # with 5×10⁴ steps we take SB3's defaults for both.
    if preset == "smoke":
        return replace(PPOConfig(total_steps=steps or SMOKE_STEPS["ppo"], learning_rate=3e-4, batch_size=64,
                                 **SMOKE_EVALUATION), **overrides)
    return replace(PPOConfig(total_steps=steps or 50_000, learning_rate=3e-4, batch_size=64), **overrides)


BASELINE_REWARDS = ("offline", "rat")  #: where preference-based SA-RL and PA-AD of a grid take r̂ from


@dataclass(frozen=True)
class GridPreset:
    """Budgets of every cell of a grid (recorded in ``grid.json``)."""

    name: str
    rat_preset: str  #: :func:`rat_config` preset
    rat_steps: int  #: RAT environment steps
    labels: dict[str, int]  #: preference labels per scenario (RAT's, and so the preference baselines'); "target": a named target's
    ppo_preset: str  #: :func:`ppo_preset` preset
    ppo_steps: int  #: SA-RL / PA-AD environment steps
    episodes: int = 30  #: final evaluation episodes per cell (the paper's 30)
    epsilon: float = 0.1
    norm: str = "linf"
    labels_by_row: dict = field(default_factory=dict)  #: per paper row "scenario/task", overriding ``labels``
    overrides: dict = field(default_factory=dict)  #: other RATConfig fields (small runs)
    pebble_overrides: dict = field(default_factory=dict)  #: other PebbleConfig fields (small runs)
    spend_by: float = 0.9  #: RAT spends its labels by this fraction of the run (cpu and smoke presets)
    #: the r̂ of preference-based SA-RL and PA-AD: "offline", learnt from the RAT cell's labels; "rat", the one
    #: the RAT cell ended with (the same labels, nothing learnt again)
    baseline_reward: str = "offline"

    def __post_init__(self):
        if self.baseline_reward not in BASELINE_REWARDS:
            raise RatError(f"baseline reward '{self.baseline_reward}': use one of {', '.join(BASELINE_REWARDS)}")


    def labels_for(self, cell: Cell) -> int:
        from rat.experiments.table1 import paper_row

        row = f"{cell.scenario}/{paper_row(cell.task, cell.scenario)}"
        # a scenario named by its target (a locomotion target, a user's behaviour) gets the "target" count
        fallback = self.labels.get("target", self.labels["manipulation"])
        return int(self.labels_by_row.get(row, self.labels.get(cell.scenario, fallback)))

    def with_labels(self, labels: dict[str, int]) -> GridPreset:
        """This preset with other label counts per scenario (``manipulation``, ``opposite``, ``target``); a
        scenario given here ignores the preset's per-row counts for it."""
        for scenario, count in labels.items():
            if scenario not in ("manipulation", "opposite", "target") or count < 0:
                raise RatError(f"labels '{scenario}={count}': give manipulation=N, opposite=N or target=N with N >= 0")
        rows = {row: n for row, n in self.labels_by_row.items() if row.split("/")[0] not in labels}
        return replace(self, labels=self.labels | labels, labels_by_row=rows)


GRID_PRESETS = {
    # The paper's budgets (a GPU cluster): 10⁶ steps for every learner, its label counts.
    "paper": GridPreset("paper", "paper", 1_000_000, {"manipulation": 9000, "opposite": 5000}, "paper", 1_000_000,
                        labels_by_row={f"opposite/{t}": n for t, n in PAPER_OPPOSITE_LABELS.items()}),
    # This project's 2-core CPU machine: 5×10⁴ steps per learner, the paper's label counts (a locomotion or
    # user target: 3,000). The behaviour-clone grid of docs/notes/table1-log.md ran with --labels
    # manipulation=3000,opposite=1000.
    "cpu": GridPreset("cpu", "cpu", 50_000, {"manipulation": 9000, "opposite": 5000, "target": 3000}, "cpu", 50_000,
                      labels_by_row={f"opposite/{t}": n for t, n in PAPER_OPPOSITE_LABELS.items()}),
    # Minutes, not results: for trying a grid or a cluster end to end.
    "smoke": GridPreset("smoke", "smoke", SMOKE_STEPS["rat"], {"manipulation": SMOKE_LABELS, "opposite": SMOKE_LABELS},
                        "smoke", SMOKE_STEPS["ppo"], episodes=SMOKE_EVALUATION["final_eval_episodes"]),
}


def attack_preset(config_class: type | None, preset: str = "cpu", budget: int | None = None, steps: int | None = None,
                  target: str = "reach", pebble_overrides: dict | None = None, spend_by: float = 0.9, **overrides):
    """The configuration (an instance of ``config_class``) under preset ``preset``, with overrides of its fields
    (``pebble_overrides`` go to RAT's PEBBLE settings).

    RAT's and PPO's settings have presets; any other attack's configuration (a plugin's, say) is its
    class's defaults with the overrides.
    """
    if config_class is RATConfig:
        return rat_config(preset, budget, steps, target, pebble_overrides, spend_by, **overrides)
    if config_class is PPOConfig:
        return ppo_preset(preset, steps, **overrides)
    if config_class is None:
        return None
    _check_preset(preset)
    fields = {f.name for f in dataclasses.fields(config_class)}
    if preset == "smoke" and "final_eval_episodes" in fields:
        overrides = {"final_eval_episodes": SMOKE_EVALUATION["final_eval_episodes"]} | overrides
    return config_class(**overrides)
