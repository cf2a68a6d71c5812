"""The paper's evaluation figures (matplotlib, PNG) from `trainers.evaluation` outcomes and summary rows.

    fig3a_xp_layouts.png    cross-play per family (e.g. "IPPO MLP IK") on each classic layout
    fig3b_gap.png           SP - XP gap per family, averaged over the classic layouts
    fig7_heldout.png        SP and XP per family on the held-out generated levels
    fig8_per_layout.png     SP and XP per family, one panel per classic layout
    heatmap_<grid>.png      where the agents stand on a grid: one row per condition, SP and XP columns (Fig. 4)
    heatmap_strangers.png   each team beside each held-out stranger: deliveries over two of the stranger's
    learning_curve.png      a run's deliveries per episode and shaped return against env steps (from its CSV logs)

A family's value on a layout comes from its conditions at home there (an SK condition on the layout it was
trained on); several conditions of one family pool their means, their standard errors add in quadrature.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: no display needed
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jax_env.layouts import COUNTER, FLOOR, GOAL, ONION_PILE, PLATE_PILE, POT  # noqa: E402

HELDOUT = "held-out"
_KIND_COLORS = {
    FLOOR: (0.96, 0.94, 0.90), COUNTER: (0.55, 0.45, 0.35), ONION_PILE: (0.95, 0.80, 0.25),
    PLATE_PILE: (0.85, 0.85, 0.90), POT: (0.25, 0.25, 0.25), GOAL: (0.35, 0.65, 0.40),
}  # fmt: skip


def family_stats(summary: list[dict], grids: str, kind: str) -> dict[str, tuple[float, float]]:
    """Family label -> (mean, s.e.) of `kind` ("sp" | "xp" | "gap") on one grid group, pooled over conditions."""
    pooled: dict[str, list[tuple[float, float]]] = {}
    for row in summary:
        if row["label"] == "cross" or not _same_group(row["grids"], grids):
            continue
        if kind == "gap":
            value, stderr = row["gap"], math.hypot(row["sp_stderr"], row["xp_stderr"])
        else:
            value, stderr = row[kind], row[f"{kind}_stderr"]
        if row[f"{'xp' if kind == 'gap' else kind}_pairs"] and not math.isnan(value):
            pooled.setdefault(row["label"], []).append((value, stderr))
    return {label: pool(values) for label, values in pooled.items()}


def pool(values: list[tuple[float, float]]) -> tuple[float, float]:
    """The mean of several (mean, s.e.) and its standard error, the errors adding in quadrature."""
    return float(np.mean([v for v, _ in values])), math.sqrt(sum(s * s for _, s in values)) / len(values)


def _same_group(row_group: str, wanted: str) -> bool:
    return row_group.startswith(HELDOUT) if wanted == HELDOUT else row_group == wanted


def _bars(axis, groups: list[str], series: dict[str, dict[str, tuple[float, float]]], ylabel: str) -> None:
    """Grouped bars: one group per x tick, one bar per series (name -> {group: (mean, s.e.)})."""
    width = 0.8 / max(1, len(series))
    for k, (name, values) in enumerate(series.items()):
        x = np.arange(len(groups)) + (k - (len(series) - 1) / 2) * width
        means = [values.get(group, (np.nan, 0))[0] for group in groups]
        errors = [values.get(group, (np.nan, 0))[1] for group in groups]
        axis.bar(x, means, width, yerr=errors, capsize=3, label=name)
    names = [g.removesuffix("_7x7").replace("_", " ") for g in groups]
    axis.set_xticks(np.arange(len(groups)), [name.replace(" ", "\n") if len(name) > 10 else name for name in names])
    axis.set_ylabel(ylabel)
    axis.grid(axis="y", alpha=0.3)
    axis.legend(fontsize=8)


def draw_figures(outcomes, summary: list[dict], out: Path) -> list[Path]:
    """The bar figures that the outcomes support (XP figures need conditions of several teams)."""
    out = Path(out)
    layouts = [grid.name for grid in outcomes.grids if not grid.name.startswith("heldout_")]
    has_heldout = len(layouts) < len(outcomes.grids)
    has_xp = any(row["xp_pairs"] for row in summary if row["label"] != "cross")
    written = []

    def save(figure, name):
        figure.tight_layout()
        figure.savefig(out / name, dpi=120)
        plt.close(figure)
        written.append(out / name)

    families = list(dict.fromkeys(row["label"] for row in summary if row["label"] != "cross"))
    if has_xp and layouts:
        xp = {label: {} for label in families}
        for layout in layouts:
            for label, stats in family_stats(summary, layout, "xp").items():
                xp[label][layout] = stats
        figure, axis = plt.subplots(figsize=(2 + 1.4 * len(layouts), 4))
        _bars(axis, layouts, xp, "cross-play deliveries per episode")
        axis.set_title("Cross-play on the classic layouts (Fig. 3a)")
        save(figure, "fig3a_xp_layouts.png")

        gaps = {}
        for label in families:
            values = [family_stats(summary, layout, "gap").get(label) for layout in layouts]
            values = [v for v in values if v is not None]
            if values:
                gaps[label] = pool(values)
        figure, axis = plt.subplots(figsize=(2 + 1.2 * len(gaps), 4))
        _bars(axis, ["classic layouts"], {label: {"classic layouts": v} for label, v in gaps.items()}, "SP - XP")
        axis.set_title("Generalisation gap, SP - XP (Fig. 3b)")
        save(figure, "fig3b_gap.png")

        figure, axes = plt.subplots(1, len(layouts), figsize=(3.2 * len(layouts), 3.8), squeeze=False)
        for axis, layout in zip(axes[0], layouts):
            series = {kind.upper(): family_stats(summary, layout, kind) for kind in ("sp", "xp")}
            present = [label for label in families if any(label in v for v in series.values())]
            _bars(axis, present, series, "deliveries per episode")
            axis.set_title(layout.removesuffix("_7x7").replace("_", " "))
        figure.suptitle("SP and XP per layout (Fig. 8)")
        save(figure, "fig8_per_layout.png")

    if has_heldout:
        series = {kind.upper(): family_stats(summary, HELDOUT, kind) for kind in ("sp", "xp")}
        series = {kind: values for kind, values in series.items() if values}
        figure, axis = plt.subplots(figsize=(2 + 1.4 * len(families), 4))
        _bars(axis, families, series, "deliveries per episode")
        axis.set_title("Held-out generated levels (Fig. 7)")
        save(figure, "fig7_heldout.png")
    return written


def grid_image(grid: np.ndarray) -> np.ndarray:
    """float RGB (H, W, 3) of a kitchen's cell kinds."""
    return np.asarray([[_KIND_COLORS[int(kind)] for kind in row] for row in grid])


def draw_heatmap(layout, panels: list[tuple[str, str, np.ndarray]], path: Path) -> Path:
    """Where agents stand on `layout`: one panel per (condition, kind, share of steps per cell [H, W]),
    conditions as rows and kinds (SP, XP) as columns, drawn over the kitchen."""
    rows = list(dict.fromkeys(condition for condition, _, _ in panels))
    kinds = list(dict.fromkeys(kind for _, kind, _ in panels))
    figure, axes = plt.subplots(len(rows), len(kinds), figsize=(3.2 * len(kinds), 3.0 * len(rows)), squeeze=False)
    background = grid_image(layout.grid)
    top = max(float(share.max()) for _, _, share in panels) or 1.0
    for axis in axes.flat:
        axis.set_axis_off()
    for condition, kind, share in panels:
        axis = axes[rows.index(condition), kinds.index(kind)]
        axis.imshow(background)
        image = axis.imshow(np.ma.masked_where(layout.grid != FLOOR, share), cmap="inferno", vmin=0, vmax=top,
                            alpha=0.85)
        axis.set_title(f"{condition}: {kind}", fontsize=9)
    figure.colorbar(image, ax=axes.ravel().tolist(), shrink=0.8, label="share of agent steps")
    figure.suptitle(f"Cells visited on {layout.name} (Fig. 4)")
    figure.savefig(path, dpi=120)
    plt.close(figure)
    return path


def draw_stranger_heatmap(teams: list[str], strangers: list[str], normalised: np.ndarray, grids: str,
                          path: Path) -> Path:
    """Team x stranger: normalised [T, S] (deliveries with the stranger over two of the stranger's, both seats
    averaged) on the grid group `grids`, each cell written in; 1.0 (white) is as good a partner as its own kind."""
    figure, axis = plt.subplots(figsize=(2.5 + 0.75 * len(strangers), 2.2 + 0.42 * len(teams)))
    top = max(2.0, float(np.nanmax(normalised)) if np.isfinite(normalised).any() else 2.0)
    norm = matplotlib.colors.TwoSlopeNorm(vmin=0.0, vcenter=1.0, vmax=top)  # white: as good as its own kind
    image = axis.imshow(normalised, cmap="RdBu", norm=norm, aspect="auto")
    for (row, column), value in np.ndenumerate(normalised):
        dark = not math.isnan(value) and abs(norm(value) - 0.5) > 0.3
        axis.text(column, row, "" if math.isnan(value) else f"{value:.2f}", ha="center", va="center", fontsize=7,
                  color="white" if dark else "black")
    axis.set_xticks(range(len(strangers)), strangers, rotation=60, ha="right", fontsize=7)
    axis.set_yticks(range(len(teams)), teams, fontsize=7)
    return _save_matrix(figure, axis, image, "over two of the stranger", f"With the held-out strangers: {grids}", path)


def draw_clash_heatmap(names: list[str], deliveries: np.ndarray, grids: str, path: Path) -> Path:
    """Convention x convention: deliveries [n, n] of the row's convention in seat 0 beside the column's in seat 1, on
    the grid group `grids`; the diagonal is each convention with itself. Cells written in for a dozen or fewer."""
    n = len(names)
    figure, axis = plt.subplots(figsize=(2.5 + 0.32 * n, 2.0 + 0.3 * n))
    image = axis.imshow(deliveries, cmap="viridis", aspect="auto")
    if n <= 12:
        for (row, column), value in np.ndenumerate(deliveries):
            axis.text(column, row, f"{value:.1f}", ha="center", va="center", fontsize=7,
                      color="black" if value > deliveries.mean() else "white")
    axis.set_xticks(range(n), names, rotation=70, ha="right", fontsize=6)
    axis.set_yticks(range(n), names, fontsize=6)
    axis.set_xlabel("seat 1", fontsize=8)
    axis.set_ylabel("seat 0", fontsize=8)
    return _save_matrix(figure, axis, image, "deliveries per episode", f"Convention x convention: {grids}", path)


def _save_matrix(figure, axis, image, label: str, title: str, path: Path) -> Path:
    """A matrix heat map's colour bar (`label`) and `title`, written to `path`."""
    figure.colorbar(image, ax=axis, fraction=0.04, pad=0.02).set_label(label, fontsize=8)
    axis.set_title(title, fontsize=9)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)
    return path


def read_scalar(run: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(env steps, values) of one scalar a run logged to CSV (`loggers` holds csv), e.g. "charts/shaped_return";
    empty arrays where it was not logged."""
    path = Path(run) / "csv" / "scalars" / f"{name}.csv"
    rows = np.loadtxt(path, delimiter=",", ndmin=2) if path.is_file() and path.stat().st_size else np.zeros((0, 2))
    return rows[:, 0], rows[:, 1]


def draw_learning_curve(run: Path, path: Path | None = None) -> Path | None:
    """learning_curve.png in the run directory: deliveries per episode (left) and the shaped return (right)
    against env steps, as logged and as a moving average; None where the run logged no CSV."""
    run = Path(run)
    curves = {name: read_scalar(run, f"charts/{name}") for name in ("episode_deliveries", "shaped_return")}
    if not any(len(steps) for steps, _ in curves.values()):
        return None
    figure, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for axis, (name, (steps, values)) in zip(axes, curves.items()):
        axis.plot(steps, values, color="tab:blue", linewidth=0.6, alpha=0.35)
        # A moving average over about 2% of the run: consecutive batches can hold different parts of an episode.
        window = max(1, len(values) // 50)
        if window > 1:
            smooth = np.convolve(values, np.ones(window) / window, mode="valid")
            axis.plot(steps[window - 1:], smooth, color="tab:blue", linewidth=1.5)
        axis.set_xlabel("env steps")
        axis.set_ylabel(name.replace("_", " ") + (" per episode" if name == "shaped_return" else ""))
        axis.grid(alpha=0.3)
    figure.suptitle(f"{run.parent.name}/{run.name}")  # the condition and seed
    figure.tight_layout()
    path = Path(path) if path is not None else run / "learning_curve.png"
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path
