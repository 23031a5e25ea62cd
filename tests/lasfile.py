"""Write small LAS/LAZ files for reader tests (one helper for every test module)."""

import numpy as np


def write_las(path, xyz, *, vlrs=(), scale=0.001, offset=(0.0, 0.0, 0.0), classes=None):
    """A LAS 1.2 point format 3 file of ``xyz`` (N, 3), intensity 0, 1, 2, ... (the
    extension decides LAZ); returns ``path``."""
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.full(3, scale)
    header.offsets = np.asarray(offset, dtype=float)
    for v in vlrs:
        header.vlrs.append(v)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.intensity = np.arange(len(xyz), dtype=np.uint16)
    if classes is not None:
        las.classification = np.asarray(classes).astype(np.uint8)
    las.write(str(path))
    return path
