"""riray engine: exact tracing and RI-Tree ray interpolation of reflective/refractive NURBS objects.

Pure Python + numpy; never imports bpy. Every import inside this package is relative so the
same files work as the installed package ``riray`` and as ``<extension>.core`` inside Blender.
"""

__version__ = "0.1.0"
