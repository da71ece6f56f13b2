#!/usr/bin/env python3
"""Runs the peers of `isovox-bench mesh` on one RAW volume and prints their figures as JSON.

VTK's vtkFlyingEdges3D (1 and 2 threads on the STDThread SMP backend, normals on) and scikit-image's
marching_cubes (single-threaded) extract the same iso-surface Isovox does. Timings are the
median of three runs of the extraction alone (the volume is already in memory).

usage: bench_mesh_peers.py RAW X Y Z u8|u16 ISO
"""
import json
import statistics
import sys
import time

import numpy as np

raw, x, y, z, kind, iso = sys.argv[1], *map(int, sys.argv[2:5]), sys.argv[5], float(sys.argv[6])
volume = np.fromfile(raw, dtype=np.uint8 if kind == "u8" else "<u2").reshape(z, y, x)
out = {}


def median_time(f, runs=3):
    times = []
    result = None
    for _ in range(runs):
        start = time.perf_counter()
        result = f()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


try:
    import vtk
    from vtk.util import numpy_support

    image = vtk.vtkImageData()
    image.SetDimensions(x, y, z)
    image.GetPointData().SetScalars(numpy_support.numpy_to_vtk(volume.ravel(), deep=True))
    for threads in (1, 2):
        smp = vtk.vtkSMPTools()
        # The PyPI wheel defaults to the Sequential backend, which ignores thread counts.
        smp.SetBackend("STDThread")
        smp.Initialize(threads)

        def run():
            fe = vtk.vtkFlyingEdges3D()
            fe.SetInputData(image)
            fe.SetValue(0, iso)
            fe.ComputeNormalsOn()
            fe.ComputeGradientsOff()
            fe.ComputeScalarsOff()
            fe.Update()
            return fe.GetOutput().GetNumberOfCells()

        seconds, triangles = median_time(run)
        out[f"vtk_{threads}"] = {"seconds": seconds, "triangles": triangles, "backend": smp.GetBackend()}
except ImportError as e:
    out["vtk_error"] = str(e)

try:
    from skimage.measure import marching_cubes

    seconds, result = median_time(lambda: marching_cubes(volume, level=iso), runs=1 if volume.size > 50e6 else 3)
    out["skimage"] = {"seconds": seconds, "triangles": len(result[1])}
except ImportError as e:
    out["skimage_error"] = str(e)

print(json.dumps(out))
