"""Regenerate the sample scene files: ``python sample_scenes/build_scenes.py [NAME ...] [--check]``.

Core only (numpy, no bpy). The scenes themselves are defined in ``riray.scene.samples``
(core/scene/samples.py); this script builds each one and writes sample_scenes/<name>.json with
``riray.scene.io.save_scene``. ``--check`` writes nothing and exits 1 if any file is missing or
differs from what would be generated.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _import_riray():
    """The installed ``riray`` package, or else the repository's core/ loaded under that name
    (every import inside core/ is relative, so this is the same code)."""
    try:
        import riray  # noqa: F401
    except ImportError:
        core = HERE.parent / "core"
        spec = importlib.util.spec_from_file_location(
            "riray", core / "__init__.py", submodule_search_locations=[str(core)])
        module = importlib.util.module_from_spec(spec)
        sys.modules["riray"] = module
        spec.loader.exec_module(module)
    from riray.scene import io, samples
    return io, samples


def main(argv=None) -> int:
    io, samples = _import_riray()
    ap = argparse.ArgumentParser(description="Regenerate sample_scenes/<name>.json.")
    ap.add_argument("names", nargs="*",
                    help=f"samples to build (default: all of {', '.join(samples.SAMPLES)})")
    ap.add_argument("--check", action="store_true",
                    help="verify the files are up to date instead of writing them")
    args = ap.parse_args(argv)
    names = args.names or list(samples.SAMPLES)
    unknown = [n for n in names if n not in samples.SAMPLES]
    if unknown:
        ap.error(f"unknown sample(s) {unknown}; choose from {', '.join(samples.SAMPLES)}")
    stale = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            scene = samples.build(name)
            target = HERE / f"{name}.json"
            out = Path(tmp) / target.name if args.check else target
            io.save_scene(scene, out)
            if args.check:
                same = target.is_file() and target.read_bytes() == out.read_bytes()
                if not same:
                    stale.append(name)
                print(f"{name:13s} {'ok' if same else 'STALE (rerun without --check)'}")
            else:
                print(f"{name:13s} {len(scene.object.patches):3d} patches  "
                      f"{out.stat().st_size / 1024:7.1f} KiB  {out}")
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
