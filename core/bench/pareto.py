"""Does the baked-error tolerance dominate the paper's angle threshold? (a Pareto judgement
from the bench's sweep rows, measuring nothing).

Per scene, every point of the angle-threshold curve (sweep "angle", its no-threshold point
included) is compared with the points of the tolerance curve (sweep "max_error": ``--max-error``
with the default mirror rays) and, separately, with every ``--max-error`` point (also the
"reflect" and "path" sweeps). A threshold point is *dominated* by a tolerance point that is at
least as fast (object-only time relative to exact: 1 / ``object_speedup``, the median of its
passes' same-pass ratios) with a mean and a 99th-percentile angular error no higher. The
curve dominates where every threshold point is dominated.
"""

from __future__ import annotations

THRESHOLD_SWEEP = "angle"
TOLERANCE_SWEEP = "max_error"
ANY_TOLERANCE_SWEEPS = ("max_error", "reflect", "path")
# Errors closer than this (degrees) are equal: the exact tracer itself agrees with independent
# references to about 1e-8 deg, and a point that traces every ray (error 0) is not better than
# one whose exact mirror hits are off by 1e-9 deg.
ERR_EQUAL_DEG = 1e-6


def _time(r) -> float:
    """Object-only time relative to exact (a speed-up of 0 would be no render: infinite)."""
    s = float(r["object_speedup"])
    return 1.0 / s if s > 0 else float("inf")


def _err(r, key) -> float:
    """A row's error; a row that interpolated nothing has none (0: nothing answered off)."""
    v = r.get(key)
    return 0.0 if v is None or v == "" else float(v)


def dominates(a, b) -> bool:
    """Whether row ``a`` is at least as fast as row ``b`` with mean and p99 errors no higher
    (within ERR_EQUAL_DEG)."""
    return (_time(a) <= _time(b)
            and _err(a, "angle_mean_deg") <= _err(b, "angle_mean_deg") + ERR_EQUAL_DEG
            and _err(a, "angle_p99_deg") <= _err(b, "angle_p99_deg") + ERR_EQUAL_DEG)


def _label(r) -> str:
    if r["sweep"] == THRESHOLD_SWEEP:
        return "no threshold" if r.get("angle") in (None, "") else f"{float(r['angle']):g} deg"
    extra = {"reflect": " reflect", "path": " path"}.get(r["sweep"], "")
    return f"{float(r['max_error']):g} deg{extra}"


def dominance(rows) -> list:
    """Per scene with threshold points: {"scene", "points": [{"threshold", "time", "mean",
    "p99", "by_curve", "by_any"}], "curve_dominates", "any_dominates",
    "curve_dominates_angles"}; ``by_curve`` and ``by_any`` list the tolerance points that
    dominate the threshold point; the last flag leaves the no-threshold point out (the
    paper's rules with nothing bounding their error: the tolerance keeps those rules' tracing
    and adds its own)."""
    out = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        rs = [r for r in rows if r["scene"] == scene]
        thr = [r for r in rs if r["sweep"] == THRESHOLD_SWEEP]
        if not thr:
            continue
        curve = [r for r in rs if r["sweep"] == TOLERANCE_SWEEP]
        anyt = [r for r in rs if r["sweep"] in ANY_TOLERANCE_SWEEPS]
        pts = [{"threshold": _label(t), "time": _time(t), "mean": _err(t, "angle_mean_deg"),
                "p99": _err(t, "angle_p99_deg"),
                "by_curve": [_label(c) for c in curve if dominates(c, t)],
                "by_any": [_label(c) for c in anyt if dominates(c, t)]} for t in thr]
        angled = [p for p, t in zip(pts, thr) if t.get("angle") not in (None, "")]
        out.append({"scene": scene, "points": pts,
                    "curve_dominates": bool(curve) and all(p["by_curve"] for p in pts),
                    "any_dominates": bool(anyt) and all(p["by_any"] for p in pts),
                    "curve_dominates_angles": bool(curve) and bool(angled)
                    and all(p["by_curve"] for p in angled)})
    return out


def dominance_markdown(rows) -> str:
    """The dominance table of ``rows`` (sweep rows), one block per scene."""
    lines = ["**Does the tolerance dominate the angle threshold?** (object-only time relative "
             "to exact, 1 / speed-up; a threshold point is dominated by a `--max-error` point at "
             "least as fast with mean and p99 no higher)", ""]
    for s in dominance(rows):
        lines += [f"{s['scene']}: tolerance curve dominates: "
                  f"**{'yes' if s['curve_dominates'] else 'no'}** (without the no-threshold "
                  f"point: {'yes' if s['curve_dominates_angles'] else 'no'}); any "
                  f"`--max-error` point (also reflect, path): "
                  f"**{'yes' if s['any_dominates'] else 'no'}**", "",
                  "| threshold | time | mean / p99 deg | dominated by the tolerance curve "
                  "| by any --max-error point |", "|---|---:|---:|---|---|"]
        for p in s["points"]:
            lines.append(f"| {p['threshold']} | {p['time']:.2f} | {p['mean']:.3f} / "
                         f"{p['p99']:.2f} | {', '.join(p['by_curve']) or 'no'} | "
                         f"{', '.join(p['by_any']) or 'no'} |")
        lines.append("")
    return "\n".join(lines)
