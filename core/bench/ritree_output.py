"""``riray bench``'s outputs: the break-even (amortization) rows, ``tables.csv``,
``sweeps.csv``, ``results.json``, ``tables.md`` and ``sweeps.md``, the plots and the per-view
images; :func:`replot` re-makes them from a results.json."""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import numpy as np

from ..ritree.query import DEFAULT_MAX_ERROR_DEG
from .pareto import dominance, dominance_markdown


def amortization(tables) -> list:
    """Per table view and interpolated row ("interp": no angle threshold, "interp_angle": with
    it, "interp_tol": the default tolerance, "deeper": it on the deeper tree): bake CPU
    seconds, per-frame total CPU seconds exact and interpolated, and the break-even frame count
    N* = bake / (exact - interpolated), the smallest N for which bake + N interpolated frames
    cost no more than N exact frames (None where interpolation saves nothing per frame: it
    never pays)."""
    out = []
    by = {}
    for r in tables:
        by.setdefault((r["scene"], r["view"]), {})[r["row"]] = r
    for (scene, view), rows in by.items():
        ex = rows["exact"]
        for kind in ("interp", "interp_angle", "interp_tol", "deeper"):
            if kind not in rows:
                continue
            it = rows[kind]
            saved = ex["total_cpu_s"] - it["total_cpu_s"]
            saved_o = ex["object_cpu_s"] - it["object_cpu_s"]
            out.append({"scene": scene, "view": view, "row": kind, "bake_cpu_s": it["bake_cpu_s"],
                        "bake_s": it["bake_s"], "exact_frame_cpu_s": ex["total_cpu_s"],
                        "interp_frame_cpu_s": it["total_cpu_s"],
                        "break_even_frames": (math.ceil(it["bake_cpu_s"] / saved)
                                              if saved > 0 else None),
                        "break_even_frames_object_only": (math.ceil(it["bake_cpu_s"] / saved_o)
                                                          if saved_o > 0 else None)})
    return out


def replot(out) -> list:
    """Re-make the derived outputs (amortization, Markdown, CSV, plots) of ``out`` from its
    results.json, measuring nothing."""
    out = Path(out)
    try:
        result = json.loads((out / "results.json").read_text(), parse_constant=float)
    except (OSError, ValueError) as e:
        raise ValueError(f"{out / 'results.json'}: cannot read a riray bench result ({e})") \
            from None
    for r in (*result["tables"], *result["sweeps"]):
        for k, v in r.items():
            if v in ("inf", "-inf"):
                r[k] = float(v)
    result["amortization"] = amortization(result["tables"])
    written = write_outputs(result, out, True)
    result["written"] = [str(p) for p in written]
    return result


TABLE_CSV = ("scene", "view", "row", "label", "rays_traced", "object_rays", "traced_fraction",
             "solved_fraction", "beyond_fraction",
             "object_cpu_s", "total_cpu_s", "object_speedup", "total_speedup",
             "query_own_cpu_s", "query_own_fraction", "pairs",
             "newton_iters", "fallback_pairs", "exact_first_hits", "exact_mirror_hits",
             "mirror_newton_cpu_s", "samples_gathered",
             "angle_mean_deg", "angle_p99_deg", "angle_max_deg", "psnr_db", "max_pixel_diff",
             "hit_disagreements", "null_disagreements", "viewpoint_depth", "direction_depth",
             "viewpoint_refine",
             "tolerance", "bake_s",
             "bake_cpu_s", "cache_bytes", "tree_samples")
SWEEP_CSV = ("scene", "view", "sweep", "viewpoint_depth", "direction_depth", "tolerance",
             "policy", "angle", "distance", "extrapolation", "max_error", "path_identity",
             "mirror_rays",
             "bake_s", "bake_cpu_s",
             "cache_bytes", "tree_samples", "bake_rays", "rays_traced", "object_rays",
             "traced_fraction", "solved_fraction", "object_cpu_s", "total_cpu_s",
             "exact_object_cpu_s",
             "exact_total_cpu_s", "object_speedup", "total_speedup", "pairs", "newton_iters",
             "samples_gathered", "angle_mean_deg", "angle_p99_deg", "angle_max_deg", "psnr_db",
             "max_pixel_diff")


def _write_csv(path, rows, cols):
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for r in rows:
            w.writerow(["" if r.get(c) is None else r.get(c) for c in cols])


def json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else ("inf" if x > 0 else "-inf")
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.generic):
        return json_safe(x.item())
    return x


def write_outputs(result, out: Path, plots=True) -> list:
    """Write the CSV, JSON and Markdown files (and the plots) of ``result`` into ``out``;
    returns the paths written."""
    written = []
    p = out / "tables.csv"
    _write_csv(p, result["tables"], TABLE_CSV)
    written.append(p)
    if result["sweeps"]:
        p = out / "sweeps.csv"
        _write_csv(p, result["sweeps"], SWEEP_CSV)
        written.append(p)
    result["pareto"] = dominance(result["sweeps"])
    p = out / "results.json"
    p.write_text(json.dumps(json_safe(result), indent=1) + "\n")
    written.append(p)
    p = out / "tables.md"
    p.write_text(tables_markdown(result) + "\n")
    written.append(p)
    if result["sweeps"]:
        p = out / "sweeps.md"
        p.write_text(sweeps_markdown(result["sweeps"]) + "\n\n"
                     + dominance_markdown(result["sweeps"]) + "\n")
        written.append(p)
    if plots:
        try:
            from . import plots as plotting
            written += plotting.plot_all(result, out)
        except ImportError as e:     # matplotlib missing: the numbers are written regardless
            print(f"riray bench: plots skipped: {e}", file=sys.stderr)
    return written


def _pct(v):
    """A fraction in percent, one decimal; "-" where the row has none (results.json of a riray
    that did not solve rays along sample paths, read by --replot)."""
    return "-" if v is None else f"{100 * v:.1f}"


def _fmt(v, f="{:.2f}"):
    if v is None:
        return "-"
    if isinstance(v, float) and not math.isfinite(v):
        return "inf"
    return f.format(v)


def err3(r) -> str:
    """"mean / p99 / max" angular error of row ``r`` (degrees)."""
    if r["angle_mean_deg"] is None:
        return "- (none interpolated)"
    return f"{r['angle_mean_deg']:.3f} / {r['angle_p99_deg']:.2f} / {r['angle_max_deg']:.1f}"


def tables_markdown(result) -> str:
    """The paper-style tables, one per scene (rows: view x method), and the break-even table."""
    lines = []
    tables = result["tables"]
    for scene in dict.fromkeys(r["scene"] for r in tables):
        rows = [r for r in tables if r["scene"] == scene]
        r0 = rows[0]
        lines += [f"**{scene}** (tree: viewpoint depth {r0['viewpoint_depth']}, direction depth "
                  f"{r0['direction_depth']}, tolerance {r0['tolerance']:g} deg)", "",
                  "| view | method | rays traced | traced % of object | solved along a "
                  "sample's path, % of object | traced or beyond "
                  f"{DEFAULT_MAX_ERROR_DEG:g} deg, % of object | object-only CPU s "
                  "| total CPU s | object-only speed-up | query's own work, % of exact "
                  "object-only | pairs | Newton it | samples gathered | mean / p99 / max err deg "
                  "| wrong hit / null | PSNR dB |",
                  "|---|---|" + "---:|" * 14]
        for r in rows:
            err = "-" if r["row"] == "exact" else err3(r)
            own = "-" if r["row"] == "exact" else f"{100 * r['query_own_fraction']:.1f}"
            lines.append(
                f"| {r['view']} | {r['label']} | {r['rays_traced']:,} of {r['object_rays']:,} | "
                f"{100 * r['traced_fraction']:.1f} | {_pct(r.get('solved_fraction'))} | "
                f"{100 * (r['traced_fraction'] + r['beyond_fraction']):.1f} | "
                f"{r['object_cpu_s']:.2f} | "
                f"{r['total_cpu_s']:.2f} | {r['object_speedup']:.2f}x | {own} | {r['pairs']:,} | "
                f"{r['newton_iters']:,} | {r['samples_gathered']:,} | {err} | "
                f"{r['hit_disagreements']} / {r['null_disagreements']} | "
                f"{_fmt(r['psnr_db'], '{:.1f}')} |")
        lines.append("")
    lines += ["**Bake and break-even** (CPU seconds per frame; N* = frames after which bake + N "
              "interpolated frames cost less than N exact ones)", "",
              "| scene | view | bake s (wall) | bake CPU s | cache MB | exact frame | interpolated "
              "frame, no threshold | N* | interpolated frame, angle threshold | N* | "
              "interpolated frame, default tolerance | N* | deeper tree: bake CPU s | cache MB "
              "| frame | N* |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    cache = {(r["scene"], r["view"], r["row"]): r["cache_bytes"] for r in tables}
    am = {(a["scene"], a["view"], a["row"]): a for a in result["amortization"]}
    for scene, view in dict.fromkeys((a["scene"], a["view"]) for a in result["amortization"]):
        a, b, c = (am[(scene, view, k)] for k in ("interp", "interp_angle", "interp_tol"))

        def be(x):
            return "never" if x["break_even_frames"] is None else f"{x['break_even_frames']:,}"
        t = am.get((scene, view, "deeper"))
        deep = ("- | - | - | -" if t is None else
                f"{t['bake_cpu_s']:.1f} | {cache[(scene, view, 'deeper')] / 1e6:.2f} | "
                f"{t['interp_frame_cpu_s']:.2f} | {be(t)}")
        lines.append(f"| {scene} | {view} | {a['bake_s']:.1f} | {a['bake_cpu_s']:.1f} | "
                     f"{cache[(scene, view, 'exact')] / 1e6:.2f} | {a['exact_frame_cpu_s']:.2f} | "
                     f"{a['interp_frame_cpu_s']:.2f} | {be(a)} | {b['interp_frame_cpu_s']:.2f} | "
                     f"{be(b)} | {c['interp_frame_cpu_s']:.2f} | {be(c)} | {deep} |")
    return "\n".join(lines)


def sweeps_markdown(rows) -> str:
    """The sweep rows as one Markdown table per scene."""
    lines = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        lines += [f"**{scene}** ({rows[0]['view']} view)", "",
                  "| sweep | vp | dir | tol | angle | dist | extrap | max err | bake s | "
                  "cache MB | traced % | solved % | object-only s (exact) | total s (exact) | "
                  "mean / p99 / max err deg | PSNR dB | max diff |",
                  "|---" + "|---:" * 16 + "|"]
        for r in (r for r in rows if r["scene"] == scene):
            lines.append(
                f"| {r['sweep']} | {r['viewpoint_depth']} | {r['direction_depth']} | "
                f"{r['tolerance']:g} | {_fmt(r['angle'], '{:g}')} | "
                f"{_fmt(r['distance'], '{:g}')} | "
                f"{_fmt(r['extrapolation'], '{:g}')} | {_fmt(r.get('max_error'), '{:g}')}"
                f"{' path' if r.get('path_identity') else ''}"
                f"{' reflect' if r.get('mirror_rays') == 'reflect' else ''} | "
                f"{r['bake_s']:.1f} | "
                f"{r['cache_bytes'] / 1e6:.2f} | {100 * r['traced_fraction']:.1f} | "
                f"{_pct(r.get('solved_fraction'))} | "
                f"{r['object_cpu_s']:.2f} ({r['exact_object_cpu_s']:.2f}) | "
                f"{r['total_cpu_s']:.2f} ({r['exact_total_cpu_s']:.2f}) | "
                f"{err3(r)} | {_fmt(r['psnr_db'], '{:.1f}')} | {r['max_pixel_diff']:.2f} |")
        lines.append("")
    return "\n".join(lines)


def save_images(folder, stem, images) -> None:
    """A view's renders as PNGs ``stem_KEY.png`` in ``folder`` (``*_traced`` masks white)."""
    from ..imageio import write_png, write_png_u8
    folder.mkdir(parents=True, exist_ok=True)
    for k, img in images.items():
        if k.endswith("_traced"):
            write_png_u8(folder / f"{stem}_{k}.png", np.where(img, 255, 0).astype(np.uint8))
        else:
            write_png(folder / f"{stem}_{k}.png", img)
