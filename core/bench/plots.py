"""Plots of a ``riray bench`` run (PNG, matplotlib with the Agg backend, imported lazily: the
engine never needs it; ``pip install 'riray[bench]'``).

- ``pareto.png``: error versus render time, one column per scene (its close view): mean and
  p99 angular error of the interpolated output rays and image PSNR against the exact render
  versus the interpolated frame's object-only time relative to the exact render's in the
  same pass (the ratio cancels the load of a shared machine, which single sweep passes do
  not); every sweep point, the render-time policies (angle threshold, baked-error tolerance,
  tolerance with path identity, on mirrors the tolerance with mirror rays from the
  interpolated normal instead of the default exact hits) as curves and the raytree policy as a point, the Pareto
  front (nothing else is both faster and more accurate) joined, the exact render at 1
  dashed.
- ``bake_depth.png``: bake wall time and cache size versus direction depth, one line per
  scene and viewpoint depth.
- ``amortized.png``: CPU seconds per frame versus frame count N, one panel per view: (bake +
  N interpolated frames) / N as a line per scene (interpolation without the angle threshold,
  the paper's Table 1 row), N exact frames / N dashed, the break-even frame count marked.
"""

from __future__ import annotations

import math
from pathlib import Path

SWEEP_MARKERS = {"depth": "o", "tolerance": "s", "angle": "^", "distance": "v",
                 "extrapolation": "D", "max_error": "P", "path": "X", "reflect": "d",
                 "raytree": "h",
                 "table": "*", "deeper tree": "p", "deeper tree, reflect": "8"}
# Sweeps drawn as curves (points joined in time order): the render-time policies compared.
CURVES = ("angle", "max_error", "path", "reflect")


def _plt():
    try:
        import matplotlib
    except ImportError as e:
        raise ImportError("plots need matplotlib: pip install 'riray[bench]' (or run riray "
                          "bench --no-plots)") from e
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    return plt


MINOR_LABEL_SPAN = 30.0   # label minor ticks of a log axis spanning less than this ratio only


def _plain(ax, x=False):
    """Plain numbers (not powers of ten) on a log axis; minor ticks labelled only where the
    axis is short enough for their labels not to collide."""
    from matplotlib.ticker import FormatStrFormatter, FuncFormatter

    def minor_for(axis):
        def fmt(value, _pos):
            lo, hi = sorted(abs(v) for v in axis.get_view_interval())
            return f"{value:g}" if lo > 0 and hi / lo < MINOR_LABEL_SPAN else ""
        return FuncFormatter(fmt)

    for axis in ([ax.yaxis, ax.xaxis] if x else [ax.yaxis]):
        axis.set_major_formatter(FormatStrFormatter("%g"))
        axis.set_minor_formatter(minor_for(axis))


def pareto_front(points):
    """Indices of the points (time, error) not dominated by another (lower-or-equal time and
    error, one strictly lower), sorted by time."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def plot_pareto(result, path):
    plt = _plt()
    rows = [dict(r) for r in result["sweeps"]]
    if not rows:     # no sweeps: the table rows (close to the same idea, fewer points)
        rows = [dict(r, sweep="table") for r in result["tables"] if r["row"] != "exact"]
    else:            # the default tolerance on the deeper tree, on the swept view
        view = result["config"]["sweep_view"]
        rows += [dict(r, sweep={"deeper": "deeper tree",
                                "deeper_reflect": "deeper tree, reflect"}[r["row"]])
                 for r in result["tables"]
                 if r["row"] in ("deeper", "deeper_reflect") and r["view"] == view]
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    if not scenes:
        return None
    fig, axes = plt.subplots(3, len(scenes), figsize=(5.2 * len(scenes), 12.0), squeeze=False)
    for j, scene in enumerate(scenes):
        rs = [r for r in rows if r["scene"] == scene]
        for i, (key, label, lower_better) in enumerate(
                (("angle_mean_deg", "mean angular error (deg)", True),
                 ("angle_p99_deg", "p99 angular error (deg)", True),
                 ("psnr_db", "PSNR vs exact (dB)", False))):
            ax = axes[i][j]
            pts = []
            for r in rs:
                v = r[key]
                if v is None or (isinstance(v, float) and not math.isfinite(v)) or \
                        (lower_better and v <= 0):
                    continue
                pts.append((1.0 / max(r["object_speedup"], 1e-9), v if lower_better else -v, r))
            for sweep in dict.fromkeys(p[2]["sweep"] for p in pts):
                sel = [p for p in pts if p[2]["sweep"] == sweep]
                if sweep in CURVES:
                    sel = sorted(sel, key=lambda p: p[0])
                ax.plot([p[0] for p in sel], [p[1] if lower_better else -p[1] for p in sel],
                        marker=SWEEP_MARKERS.get(sweep, "o"), alpha=0.75, label=sweep,
                        ls="-" if sweep in CURVES else "none", lw=0.8,
                        color=f"C{list(SWEEP_MARKERS).index(sweep) % 10}"
                        if sweep in SWEEP_MARKERS else None)
            front = [pts[k] for k in pareto_front([(p[0], p[1]) for p in pts])]
            if front:
                ax.plot([p[0] for p in front], [p[1] if lower_better else -p[1] for p in front],
                        "k-", lw=1.2, label="Pareto front", zorder=0)
                ax.scatter([p[0] for p in front],
                           [p[1] if lower_better else -p[1] for p in front],
                           s=90, facecolors="none", edgecolors="k", lw=1.2)
            ax.axvline(1.0, color="r", ls="--", lw=1, label="exact render")
            if lower_better:
                ax.set_yscale("log")
                _plain(ax)
            ax.set_xlabel("object-only time, interpolated / exact (same pass)")
            ax.set_ylabel(label)
            ax.set_title(f"{scene} ({rs[0]['view']})")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_bake_depth(result, path):
    plt = _plt()
    rows = [r for r in result["sweeps"] if r["sweep"] == "depth"]
    if not rows:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.3))
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for vp in sorted({r["viewpoint_depth"] for r in rows if r["scene"] == scene}):
            rs = sorted((r for r in rows if r["scene"] == scene and r["viewpoint_depth"] == vp),
                        key=lambda r: r["direction_depth"])
            x = [r["direction_depth"] for r in rs]
            lab = f"{scene}, viewpoint depth {vp}"
            axes[0].plot(x, [r["bake_s"] for r in rs], "o-", label=lab)
            axes[1].plot(x, [r["cache_bytes"] / 1e6 for r in rs], "o-", label=lab)
    for ax, yl in zip(axes, ("bake wall time (s)", "cache file size (MB)")):
        ax.set_xlabel("maximum direction-tree depth")
        ax.set_ylabel(yl)
        ax.set_yscale("log")
        _plain(ax)
        ax.set_xticks(sorted({r["direction_depth"] for r in rows}))
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_amortized(result, path, n_max=10000):
    plt = _plt()
    am = [a for a in result["amortization"] if a.get("row", "interp") == "interp"]
    if not am:
        return None
    views = list(dict.fromkeys(a["view"] for a in am))
    fig, axes = plt.subplots(1, len(views), figsize=(5.2 * len(views), 4.3), squeeze=False)
    ns = [round(10 ** (k / 20)) for k in range(0, int(20 * math.log10(n_max)) + 1)]
    for ax, view in zip(axes[0], views):
        for k, a in enumerate(x for x in am if x["view"] == view):
            c = f"C{k}"
            ax.plot(ns, [(a["bake_cpu_s"] + n * a["interp_frame_cpu_s"]) / n for n in ns], "-",
                    color=c, label=f"{a['scene']}: bake + N interpolated")
            ax.axhline(a["exact_frame_cpu_s"], color=c, ls="--", lw=1)
            be = a["break_even_frames"]
            if be is not None and be <= n_max:
                ax.axvline(be, color=c, ls=":", lw=1)
                ax.plot([be], [a["exact_frame_cpu_s"]], "o", color=c)
                ax.annotate(f"N*={be}", (be, a["exact_frame_cpu_s"]), fontsize=7,
                            textcoords="offset points", xytext=(4, 4), color=c)
        ax.set_xscale("log")
        ax.set_yscale("log")
        _plain(ax, x=True)
        ax.set_xlabel("frames N")
        ax.set_ylabel("CPU s per frame (dashed: exact)")
        ax.set_title(f"{view} view: amortized time per frame")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_all(result, out) -> list:
    out = Path(out)
    made = [plot_pareto(result, out / "pareto.png"),
            plot_bake_depth(result, out / "bake_depth.png"),
            plot_amortized(result, out / "amortized.png")]
    return [p for p in made if p is not None]
