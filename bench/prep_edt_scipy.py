"""Times scipy.ndimage.distance_transform_edt on a mask palpsim-bench prep wrote.

usage: python prep_edt_scipy.py MASK.raw NX NY NZ SX SY SZ OUT.raw REPEATS
MASK.raw: uint8, i fastest (the patient grid); the distance is taken inside the
mask to its zero voxels, in mm with spacing (SX, SY, SZ). Writes the distances as
float32 to OUT.raw and prints one JSON line with the best time in seconds.
"""
import json
import sys
import time

import numpy as np
import scipy
import scipy.ndimage

path, nx, ny, nz, sx, sy, sz, out, repeats = sys.argv[1:10]
nx, ny, nz, repeats = int(nx), int(ny), int(nz), int(repeats)
mask = np.fromfile(path, dtype=np.uint8).reshape(nz, ny, nx)
best = float("inf")
for _ in range(repeats):
    t0 = time.perf_counter()
    d = scipy.ndimage.distance_transform_edt(mask, sampling=(float(sz), float(sy), float(sx)))
    best = min(best, time.perf_counter() - t0)
d.astype(np.float32).tofile(out)
print(json.dumps({"seconds": best, "scipy": scipy.__version__, "numpy": np.__version__}))
