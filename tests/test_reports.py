"""Attack reports: the clean victim's success stands beside the attack's, and says when a target is vacuous."""

from rat.reports import AttackReport

BASE = dict(method="rat", reward="labels", victim="zoo:drawer-open-v3", task="drawer-close-v3", target="opposite",
            epsilon=0.1, norm="linf", seed=0, attack_success_rate=1.0, attack_success_ci=[0.886, 1.0], episodes=30,
            max_perturbation=0.1, mean_perturbation=0.08)


def test_a_report_says_when_the_clean_victim_already_reaches_the_target():
    vacuous = AttackReport(**BASE, clean_success_rate=29 / 30).summary()
    assert "the clean victim: 96.7%" in vacuous and "reaches this target on its own" in vacuous
    real = AttackReport(**BASE, clean_success_rate=0.0).summary()
    assert "the clean victim: 0.0%" in real and "on its own" not in real


def test_a_report_written_before_clean_success_was_recorded_still_reads(tmp_path):
    (tmp_path / "report.json").write_text(__import__("json").dumps(BASE))
    report = AttackReport.read(tmp_path)
    assert report.clean_success_rate is None and "clean victim" not in report.summary()


def test_the_training_plot_marks_the_deployed_attack_where_evaluations_measured_something_else(tmp_path):
    """A RAT run that refines Δ is evaluated during training on the network's Δ alone (0% on a manipulation row
    whose refined attack makes 93%); the plot must show the deployed result, not only the 0% line."""
    import matplotlib.image

    from rat.plots import plot_training

    metrics = tmp_path / "metrics.csv"
    metrics.write_text("step,eval_success_rate\n100,\n1000,0.0\n2000,0.0\n")

    def red_pixels(path):
        rgb = matplotlib.image.imread(path)[..., :3]
        return int(((rgb[..., 0] > 0.75) & (rgb[..., 1] < 0.3) & (rgb[..., 2] < 0.3)).sum())

    assert red_pixels(plot_training(metrics, tmp_path / "plain.png", "t")) == 0
    marked = plot_training(metrics, tmp_path / "marked.png", "t", curve="the network's Δ alone",
                           final=(2000, 0.933, "the attack, Δ refined"))
    assert red_pixels(marked) > 50


def test_a_rat_training_plot_names_its_victim_and_where_the_behaviour_is_sought(tmp_path):
    """Two all-zero runs' plots were byte for byte the same: a reader could not tell which run a plot was of."""
    from PIL import Image

    from rat.attacks.rat import training_title
    from rat.plots import plot_training

    opposite = {"victim": "zoo:window-open-v3", "victim_task": "window-open-v3", "task": "window-close-v3"}
    assert training_title("opposite", opposite) == "RAT opposite against zoo:window-open-v3 in window-close-v3"
    assert training_title("reach", dict(opposite, task="window-open-v3")) == "RAT reach against zoo:window-open-v3"
    assert training_title("reach", {}) == "RAT reach"  # a setup built in code, with nothing described
    metrics = tmp_path / "metrics.csv"
    metrics.write_text("step,eval_success_rate\n1000,0.0\n")
    title = training_title("opposite", opposite)
    png = plot_training(metrics, tmp_path / "training.png", f"{title}\nattack success during training")
    assert Image.open(png).text["Title"] == f"{title} attack success during training"  # readable without looking
