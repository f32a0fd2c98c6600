"""The package's one figure style: a name and a colour per method, summaries over seeds that no diverging seed drags."""

import numpy as np
import pandas as pd


def test_one_style_for_every_method():
    from sb3_lifelong.experiments.presets import ONLINE, STUDENTS
    from sb3_lifelong.experiments.style import METHODS, method_color

    known = ["MPO", *(f"online {name}" for name in ONLINE), *STUDENTS]
    assert set(known) <= set(METHODS)  # every method of the studies has its name and colour
    assert len({style.color for style in METHODS.values()}) == len(METHODS)
    assert len({style.label for style in METHODS.values()}) == len(METHODS)
    others = ["x", "y", "MPO", "z"]
    colors = [method_color(name, others) for name in others]
    assert len(set(colors)) == 4 and not set(colors) - {METHODS["MPO"].color} & {s.color for s in METHODS.values()}


def test_a_diverging_seed_drags_no_summary():
    """Q over seeds: one line per seed, the median and an interquartile band of the seeds' own values."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sb3_lifelong.experiments.style import seed_lines, value_scale

    steps = np.arange(1, 7) * 5000
    rows = [dict(seed=s, timesteps=t, q=100.0 + s + k) for s in range(3) for k, t in enumerate(steps)]
    rows += [dict(seed=3, timesteps=t, q=100.0 * 3.0**k) for k, t in enumerate(steps)]  # diverges to 24,300
    frame = pd.DataFrame(rows)
    fig, ax = plt.subplots()
    assert seed_lines(ax, frame, "student", "red", y="q") == 4
    lines = [line for line in ax.get_lines() if len(line.get_xdata())]
    assert len(lines) == 5  # four seeds and their median
    median = lines[-1].get_ydata()
    assert median.max() < 110 and lines[-1].get_label() == "student (n=4)"
    band = ax.collections[0].get_paths()[0].vertices[:, 1]
    assert band.max() < 110  # the upper quartile is a seed's own value, not a point pulled towards the diverged one
    assert value_scale(ax, list(frame["q"]), "average Q") == "average Q (log scale)" and ax.get_yscale() == "log"
    plt.close(fig)
    fig, ax = plt.subplots()
    seed_lines(ax, frame[frame["seed"] < 2], "student", "red", y="q")
    assert len([line for line in ax.get_lines() if len(line.get_xdata())]) == 2 and not ax.collections  # no summary
    assert value_scale(ax, [100.0, 120.0], "average Q") == "average Q" and ax.get_yscale() == "linear"
    plt.close(fig)
