"""The formats' benchmark (run by scripts/bench-formats.sh, which starts the two servers).

1. tensorstore (zarr3 driver, its cache off) reads level 0 whole through isovox serve's Zarr
   view and through nginx serving the exported chunks, rounds alternating; prints MB/s of
   decoded voxels (median of the rounds) and the ratio, after checking both read equal.
2. isovox import of the same voxels written by zarr-python, cloud-volume, nibabel and tifffile;
   prints MB/s of input voxels (the better of two runs, page cache warm).
"""

import argparse
import os
import statistics
import subprocess
import time

import nibabel as nib
import numpy as np
import tensorstore as ts
import tifffile
import zarr
from cloudvolume import CloudVolume


def read_level(url, level=0):
    context = ts.Context({"cache_pool": {"total_bytes_limit": 0}})
    store = ts.open({"driver": "zarr3", "kvstore": f"{url}/{level}/"}, context=context).result()
    start = time.perf_counter()
    data = store.read().result()
    return data, time.perf_counter() - start


def bench_reads(isovox, nginx, rounds, placement):
    a, _ = read_level(isovox)
    b, _ = read_level(nginx)
    if not np.array_equal(a, b):
        raise SystemExit("isovox and nginx returned different voxels")
    mb = a.nbytes / 1e6
    times = {"isovox serve (Zarr view)": [], "nginx (exported chunks)": []}
    for _ in range(rounds):
        for name, url in (("isovox serve (Zarr view)", isovox), ("nginx (exported chunks)", nginx)):
            times[name].append(read_level(url)[1])
    print(f"\ntensorstore zarr3, level 0 whole ({a.shape[2]}x{a.shape[1]}x{a.shape[0]} u8, {mb:.0f} MB decoded), {rounds} rounds each, {placement}\n")
    print("| server | median s | MB/s | best MB/s |")
    print("|---|---:|---:|---:|")
    medians = {}
    for name, t in times.items():
        medians[name] = statistics.median(t)
        print(f"| {name} | {medians[name]:.3f} | {mb / medians[name]:.0f} | {mb / min(t):.0f} |")
    ratio = medians["nginx (exported chunks)"] / medians["isovox serve (Zarr view)"]
    print(f"\nisovox / nginx: {ratio:.2f}x (throughput, medians)")


def timed(cmd):
    start = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - start


def bench_imports(bin_, work, raw_from):
    os.makedirs(work, exist_ok=True)
    raw = os.path.join(work, "world.raw")
    subprocess.run([bin_, "export", raw_from, "-o", raw], check=True)
    info = subprocess.run([bin_, "inspect", raw_from, "--json"], check=True, capture_output=True, text=True).stdout
    import json

    dx, dy, dz = json.loads(info)["dims"]
    vol = np.fromfile(raw, np.uint8).reshape(dz, dy, dx)
    inputs = []
    p = os.path.join(work, "v3.zarr")
    z = zarr.create_array(p, shape=vol.shape, chunks=(64, 64, 64), dtype="uint8")
    z[...] = vol
    inputs.append(("Zarr v3 (zarr-python, zstd)", p))
    p = os.path.join(work, "v2.zarr")
    from numcodecs import Blosc

    z = zarr.create_array(p, shape=vol.shape, chunks=(64, 64, 64), dtype="uint8", zarr_format=2,
                          compressors=Blosc(cname="lz4", clevel=5))
    z[...] = vol
    inputs.append(("Zarr v2 (zarr-python, blosc lz4)", p))
    for compress in (False, "gzip"):
        p = os.path.join(work, f"pre-{compress or 'raw'}")
        cv_info = CloudVolume.create_new_info(
            num_channels=1, layer_type="image", data_type="uint8", encoding="raw",
            resolution=[1, 1, 1], voxel_offset=[0, 0, 0], chunk_size=[64, 64, 64],
            volume_size=[dx, dy, dz],
        )
        cv = CloudVolume(f"file://{p}", info=cv_info, compress=compress, progress=False)
        cv.commit_info()
        cv[:, :, :] = vol.transpose(2, 1, 0)[..., None]
        inputs.append((f"precomputed (cloud-volume, {compress or 'raw'})", p))
    for name in ("v.nii", "v.nii.gz"):
        p = os.path.join(work, name)
        nib.save(nib.Nifti1Image(vol.transpose(2, 1, 0), np.eye(4)), p)
        inputs.append((f"NIfTI-1 {name[1:]} (nibabel)", p))
    p = os.path.join(work, "stack.tif")
    tifffile.imwrite(p, vol)
    inputs.append(("TIFF multi-page (tifffile)", p))
    inputs.append(("RAW (for reference)", raw))
    print(f"\nisovox import, {dx}x{dy}x{dz} u8 ({vol.nbytes / 1e6:.0f} MB of voxels), brick 32, zstd 5; the better of two runs\n")
    print("| input | s | MB/s |")
    print("|---|---:|---:|")
    out = os.path.join(work, "imported.vod")
    for name, path in inputs:
        extra = ["--dims", f"{dx},{dy},{dz}"] if path == raw else []
        best = min(timed([bin_, "import", path, "-o", out, *extra]) for _ in range(2))
        print(f"| {name} | {best:.2f} | {vol.nbytes / 1e6 / best:.0f} |")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--isovox", required=True)
    p.add_argument("--nginx", required=True)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--bin", required=True)
    p.add_argument("--work", required=True)
    p.add_argument("--raw-from", required=True)
    p.add_argument("--placement", default="client and servers sharing every core")
    p.add_argument("--reads-only", action="store_true")
    a = p.parse_args()
    bench_reads(a.isovox, a.nginx, a.rounds, a.placement)
    if not a.reads_only:
        bench_imports(a.bin, a.work, a.raw_from)


if __name__ == "__main__":
    main()
