"""The viewers: the desktop app (``gui*``, Open3D), the rerun recorder and the check's
recording. This package itself is light (no Open3D, rerun or app module is imported
here): the command line's parser reads :data:`STAGES` from it without importing the app.
"""

#: Stages the app shows, in pipeline order; "surface" is marching cubes on the final field.
STAGES = ("scan", "prepare", "hgmm", "gmr", "gp", "surface")
