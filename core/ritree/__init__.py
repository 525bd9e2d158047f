"""The RI-Tree (ray-interpolant tree, Atalay & Mount): baking, storage (``cache``: the ``.rit``
file format, docs/tree-format.md; ``codec``: compact vector/point encodings) and lookup."""
