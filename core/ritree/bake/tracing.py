"""Tracing the bake's sample rays with the exact object function, in chunks over worker
processes, with progress and cancelling between chunks."""

from __future__ import annotations

from ...parallel import map_chunks
from ...trace.objectfn import EventRecord
from ..dircube import cube_to_dir
from ..tree import Samples


class BakeCancelled(Exception):
    """The bake was cancelled; nothing was written."""


class Tracer:
    """Traces batches of (viewpoint, cube face, u, v) sample rays of ``state``'s viewpoints
    with the exact f, counting them in ``state.stats.rays``; ``kind`` ("level" or "extra")
    tells ``progress`` which kind of work the next call is."""

    def __init__(self, cfg, state, progress):
        self.cfg, self.state, self.progress = cfg, state, progress
        self.kind = "level"

    def __call__(self, vp, face, u, v) -> Samples:
        o = self.state.vp_pos[vp]
        d = cube_to_dir(face, u, v)
        cfg = self.cfg

        def work(a, b):
            rec = EventRecord.empty(b - a)
            return Samples.from_rays(cfg.st.object_function(o[a:b], d[a:b], record=rec), rec)

        def prog(frac):
            if cfg.cancel is not None and cfg.cancel():
                raise BakeCancelled("bake cancelled")
            self.progress.tracing(frac)

        self.progress.begin(self.kind, len(o))
        parts = map_chunks(work, len(o), cfg.chunk, cfg.workers, prog) if len(o) else []
        self.progress.end()
        self.state.stats.rays += len(o)
        out = Samples.empty()
        for p in parts:
            out.extend(p)
        return out
