"""Imports round-trip: volumes written by the field's own writers import to the same voxels, and
an export reads back equal in the field's readers; bad inputs fail clearly and leave nothing.

Writers: zarr-python (Zarr v3, and v2 with blosc), ome-zarr (an OME-Zarr image with a voxel
scale), cloud-volume (precomputed, raw and gzip chunks, a voxel offset; segmentations in
compressed_segmentation, uint32 and uint64, as a label channel), nibabel (NIfTI-1 .nii
and .nii.gz, with the voxel size in the header), tifffile (a multi-page file and a folder of
pages). Each is imported with the `isovox` binary and exported back to RAW (`isovox export`),
which must equal the array written. Wider types are checked against the window mapping computed
here with numpy. `isovox export --format zarr|precomputed` of a served volume must read back
equal to `/levels/{k}?format=voxels` in zarr-python and cloud-volume.

Usage: python imports_round_trip.py --isovox BIN --work DIR --url http://127.0.0.1:PORT --data DATADIR VOLUME
"""

import argparse
import json
import os
import shutil
import subprocess
import sys

import nibabel as nib
import numpy as np
import tifffile
import zarr
from cloudvolume import CloudVolume
from ome_zarr.io import parse_url
from ome_zarr.writer import write_image

from common import dtype_of, fetch_json, level_voxels

failures = []


def run(isovox, *args, ok=True):
    r = subprocess.run([isovox, *args], capture_output=True, text=True, timeout=300)
    if ok and r.returncode != 0:
        failures.append(f"isovox {' '.join(args)} failed: {r.stderr.strip()}")
    return r


def import_and_read(isovox, work, source, shape_zyx, dtype, *extra):
    """Imports `source`, exports level 0 to RAW; returns (array [z, y, x], import output, inspect)."""
    vod = os.path.join(work, "imported.vod")
    raw = os.path.join(work, "imported.raw")
    for f in (vod, raw):
        if os.path.exists(f):
            os.remove(f)
    r = run(isovox, "import", source, "-o", vod, "--brick", "16", *extra)
    if r.returncode != 0:
        return None, r.stdout, None
    run(isovox, "export", vod, "-o", raw)
    inspect = json.loads(run(isovox, "inspect", vod, "--json").stdout)
    got = np.fromfile(raw, dtype=np.dtype(dtype).newbyteorder("<")).reshape(shape_zyx)
    return got, r.stdout, inspect


def same(what, got, want):
    if got is None:
        failures.append(f"{what}: the import failed")
    elif got.dtype != want.dtype:
        failures.append(f"{what}: {got.dtype}, expected {want.dtype}")
    elif got.shape != want.shape or not np.array_equal(got, want):
        failures.append(f"{what}: the imported voxels differ ({np.count_nonzero(got != want)} of {want.size})")
    else:
        print(f"{what}: equal")


def window(values, lo, hi, high):
    """The documented mapping: round((v - lo) / (hi - lo) * H), clamped; half away from zero."""
    t = (values.astype(np.float64) - lo) * high / (hi - lo)
    t = np.where(np.isnan(t), 0, t)
    return np.clip(np.floor(t + 0.5), 0, high)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--isovox", required=True)
    p.add_argument("--work", required=True)
    p.add_argument("--url", required=True)
    p.add_argument("--data", required=True)
    p.add_argument("volume")
    a = p.parse_args()
    work = a.work
    os.makedirs(work, exist_ok=True)
    rng = np.random.default_rng(17)
    shape = (37, 45, 53)  # z, y, x: odd, not multiples of any brick
    u8 = rng.integers(0, 256, shape, dtype=np.uint8)
    u16 = rng.integers(0, 65536, shape, dtype=np.uint16)

    # zarr-python: v3 (default codecs: bytes + zstd) and v2 with blosc.
    z3 = zarr.create_array(os.path.join(work, "v3.zarr"), shape=shape, chunks=(16, 16, 16), dtype="uint8")
    z3[...] = u8
    got, _, _ = import_and_read(a.isovox, work, os.path.join(work, "v3.zarr"), shape, np.uint8)
    same("zarr-python v3 uint8", got, u8)
    from numcodecs import Blosc

    z2 = zarr.create_array(
        os.path.join(work, "v2.zarr"), shape=shape, chunks=(10, 20, 30), dtype="uint16",
        zarr_format=2, compressors=Blosc(cname="lz4", clevel=5),
    )
    z2[...] = u16
    got, _, _ = import_and_read(a.isovox, work, os.path.join(work, "v2.zarr"), shape, np.uint16)
    same("zarr-python v2 uint16 (blosc)", got, u16)

    # ome-zarr: an OME-Zarr image with a voxel size; the finest level is imported.
    store = parse_url(os.path.join(work, "ome.zarr"), mode="w").store
    root = zarr.group(store=store)
    write_image(
        u16, root, axes="zyx", scale={"z": 2.0, "y": 0.5, "x": 0.25},
        scale_factors=[{"z": 2, "y": 2, "x": 2}],
    )
    got, _, inspect = import_and_read(a.isovox, work, os.path.join(work, "ome.zarr"), shape, np.uint16)
    same("ome-zarr image uint16", got, u16)
    if inspect and inspect["voxel_scale"] != [0.25, 0.5, 2.0]:
        failures.append(f"ome-zarr: voxel scale {inspect['voxel_scale']}, expected [0.25, 0.5, 2.0] (x, y, z)")

    # cloud-volume: precomputed, raw and gzip chunks, a voxel offset, chunks unlike the brick.
    for compress in (False, "gzip"):
        path = os.path.join(work, f"pre-{compress or 'raw'}")
        info = CloudVolume.create_new_info(
            num_channels=1, layer_type="image", data_type="uint16", encoding="raw",
            resolution=[4, 5, 6], voxel_offset=[3, 5, 7], chunk_size=[16, 16, 8],
            volume_size=[shape[2], shape[1], shape[0]],
        )
        cv = CloudVolume(f"file://{path}", info=info, compress=compress, progress=False)
        cv.commit_info()
        cv[3:3 + shape[2], 5:5 + shape[1], 7:7 + shape[0]] = u16.transpose(2, 1, 0)[..., None]
        got, _, inspect = import_and_read(a.isovox, work, path, shape, np.uint16)
        same(f"cloud-volume precomputed uint16 ({compress or 'raw'} chunks)", got, u16)
        if inspect and inspect["voxel_scale"] != [4.0, 5.0, 6.0]:
            failures.append(f"cloud-volume: voxel scale {inspect['voxel_scale']}, expected [4, 5, 6]")

    # nibabel: NIfTI-1, i fastest; the voxel size from the header.
    xyz = u8.transpose(2, 1, 0)
    nib.save(nib.Nifti1Image(xyz, np.diag([0.5, 0.75, 2.0, 1.0])), os.path.join(work, "v.nii"))
    got, _, inspect = import_and_read(a.isovox, work, os.path.join(work, "v.nii"), shape, np.uint8)
    same("nibabel .nii uint8", got, u8)
    if inspect and inspect["voxel_scale"] != [0.5, 0.75, 2.0]:
        failures.append(f"nibabel: voxel scale {inspect['voxel_scale']}, expected [0.5, 0.75, 2.0]")
    i16 = rng.integers(-1000, 3000, shape, dtype=np.int16)
    nib.save(nib.Nifti1Image(i16.transpose(2, 1, 0), np.eye(4)), os.path.join(work, "ct.nii.gz"))
    got, out, _ = import_and_read(
        a.isovox, work, os.path.join(work, "ct.nii.gz"), shape, np.uint16, "--window", "-500,2500"
    )
    same("nibabel .nii.gz int16 through --window -500,2500", got, window(i16, -500, 2500, 65535).astype(np.uint16))
    if "--window" not in out:
        failures.append(f"nibabel int16: the output does not say the window was given: {out!r}")
    f32 = rng.normal(10.0, 3.0, shape).astype(np.float32)
    nib.save(nib.Nifti1Image(f32.transpose(2, 1, 0), np.eye(4)), os.path.join(work, "f.nii.gz"))
    got, out, _ = import_and_read(
        a.isovox, work, os.path.join(work, "f.nii.gz"), shape, np.uint8, "--type", "u8", "--percentiles", "1,99"
    )
    flat = np.sort(f32.ravel().astype(np.float64))
    lo, hi = flat[round(0.01 * (flat.size - 1))], flat[round(0.99 * (flat.size - 1))]
    same("nibabel float32 through its 1st and 99th percentiles", got, window(f32, lo, hi, 255).astype(np.uint8))
    if "percentiles" not in out:
        failures.append(f"nibabel float32: the output does not say percentiles were used: {out!r}")

    # A NIfTI label map (uint32 ids, as segmentation tools write them) beside the image, as the
    # channel `label`; read back through the exported Zarr view's label image, equal to the map.
    seg = np.zeros(shape, dtype=np.uint32)
    seg[5:20, 10:30, 8:40] = 7
    seg[12:30, 2:15, 30:50] = 40000
    seg[0:3, :, :] = 3
    seg[20:26, 30:40, 40:60] = 4_000_000_000
    nib.save(nib.Nifti1Image(seg.transpose(2, 1, 0), np.eye(4)), os.path.join(work, "seg.nii.gz"))
    labelled = os.path.join(work, "labelled.vod")
    r = run(a.isovox, "import", os.path.join(work, "v.nii"), "-o", labelled, "--brick", "16",
            "--channel", f"label={os.path.join(work, 'seg.nii.gz')}")
    if r.returncode == 0:
        if "channel label (u32, sparse)" not in r.stdout:
            failures.append(f"label import: the output does not name the channel: {r.stdout!r}")
        exported = os.path.join(work, "labelled-zarr")
        shutil.rmtree(exported, ignore_errors=True)
        run(a.isovox, "export", labelled, "-o", exported, "--format", "zarr")
        got = zarr.open_group(exported, mode="r")["labels"]["label"]["0"][...]
        same("NIfTI uint32 label map as channel label", got, seg)
        same("the image beside it", zarr.open_group(exported, mode="r")["0"][...], u8)
    # cloud-volume: precomputed segmentations in compressed_segmentation (its encoder is the
    # `compressed-segmentation` package), uint32 and uint64, gzip chunks and plain, chunks that
    # are not whole 8^3 blocks; imported as the channel `label` of their own type, read back as
    # above. The uint64 map holds ids past 2^53 (where a float64 would round them) and past 2^63.
    seg64 = seg.astype(np.uint64)
    seg64[2:10, 20:30, 5:15] = 2**53 + 1
    seg64[28:32, 0:8, 50:56] = 2**63 + 5
    for data_type, compress, want in (("uint32", "gzip", seg), ("uint64", False, seg64)):
        path = os.path.join(work, f"seg-{data_type}")
        shutil.rmtree(path, ignore_errors=True)
        info = CloudVolume.create_new_info(
            num_channels=1, layer_type="segmentation", data_type=data_type,
            encoding="compressed_segmentation", resolution=[1, 1, 1], voxel_offset=[0, 0, 0],
            chunk_size=[20, 12, 9], volume_size=[shape[2], shape[1], shape[0]],
        )
        cv = CloudVolume(f"file://{path}", info=info, compress=compress, progress=False)
        cv.commit_info()
        cv[:, :, :] = want.transpose(2, 1, 0)[..., None]
        out = os.path.join(work, f"labelled-{data_type}.vod")
        r = run(a.isovox, "import", os.path.join(work, "v.nii"), "-o", out, "--brick", "16",
                "--channel", f"label=precomputed://{path}")
        if r.returncode == 0:
            exported = os.path.join(work, f"labelled-{data_type}-zarr")
            shutil.rmtree(exported, ignore_errors=True)
            run(a.isovox, "export", out, "-o", exported, "--format", "zarr")
            got = zarr.open_group(exported, mode="r")["labels"]["label"]["0"][...]
            same(f"cloud-volume {data_type} compressed_segmentation as channel label", got, want)

    # A label map of another shape, or with a negative id, is refused and leaves nothing.
    big = seg.astype(np.int32)
    big[1, 1, 1] = -70000
    nib.save(nib.Nifti1Image(big.transpose(2, 1, 0), np.eye(4)), os.path.join(work, "big.nii.gz"))
    nib.save(nib.Nifti1Image(seg[:, :, :50].transpose(2, 1, 0), np.eye(4)), os.path.join(work, "small.nii.gz"))
    for bad, words in [("big.nii.gz", "-70000"), ("small.nii.gz", "shape")]:
        out = os.path.join(work, "refused.vod")
        r = run(a.isovox, "import", os.path.join(work, "v.nii"), "-o", out, "--channel",
                f"label={os.path.join(work, bad)}", ok=False)
        if r.returncode == 0 or words not in r.stderr or os.path.exists(out):
            failures.append(f"label map {bad}: exit {r.returncode}, stderr {r.stderr.strip()!r}, left a file: {os.path.exists(out)}")

    # tifffile: a multi-page file and a folder of single pages (named so that a text sort
    # would misorder them).
    tifffile.imwrite(os.path.join(work, "stack.tif"), u16)
    got, _, _ = import_and_read(a.isovox, work, os.path.join(work, "stack.tif"), shape, np.uint16)
    same("tifffile multi-page uint16", got, u16)
    folder = os.path.join(work, "pages")
    os.makedirs(folder, exist_ok=True)
    for z in range(shape[0]):
        tifffile.imwrite(os.path.join(folder, f"slice{z}.tif"), u8[z])
    got, _, _ = import_and_read(a.isovox, work, folder, shape, np.uint8)
    same("tifffile folder of pages uint8", got, u8)

    bad_inputs(a.isovox, work)
    exports(a.isovox, work, a.url, a.data, a.volume)
    if failures:
        sys.exit("\n".join(failures))
    print("every import round-tripped, every export read back equal, every bad input was refused")


def truncated_copy(work, name):
    """A copy of precomputed volume `name` whose first chunk lost its second half."""
    copy = os.path.join(work, f"{name}-truncated")
    shutil.copytree(os.path.join(work, name), copy)
    chunk_dir = os.path.join(copy, sorted(d for d in os.listdir(copy) if d != "info")[0])
    victim = os.path.join(chunk_dir, sorted(os.listdir(chunk_dir))[0])
    with open(victim, "rb") as f:
        data = f.read()
    with open(victim, "wb") as f:
        f.write(data[: len(data) // 2])
    return copy


def bad_inputs(isovox, work):
    """Each must fail with a message naming the problem, and leave no output (not even a
    temporary file)."""
    cases = []
    # A truncated precomputed chunk, plain and gzip (which then does not decompress).
    cases.append(("truncated chunk", [truncated_copy(work, "pre-raw")], "truncated"))
    cases.append(("truncated gzip chunk", [truncated_copy(work, "pre-gzip")], "cannot read"))
    # A data type Isovox does not read.
    zc = zarr.create_array(os.path.join(work, "complex.zarr"), shape=(4, 4, 4), dtype="complex64")
    zc[...] = 1
    cases.append(("complex zarr", [os.path.join(work, "complex.zarr")], "not supported"))
    nii = nib.Nifti1Image(np.zeros((4, 4, 4), np.complex64), np.eye(4))
    nib.save(nii, os.path.join(work, "complex.nii"))
    cases.append(("complex NIfTI", [os.path.join(work, "complex.nii")], "datatype"))
    # A directory named as Zarr without zarr.json.
    os.makedirs(os.path.join(work, "empty.zarr"), exist_ok=True)
    cases.append(("missing zarr.json", ["zarr://" + os.path.join(work, "empty.zarr")], "zarr.json"))
    # A truncated NIfTI.
    with open(os.path.join(work, "v.nii"), "rb") as f:
        data = f.read()
    with open(os.path.join(work, "short.nii"), "wb") as f:
        f.write(data[: len(data) - 1000])
    cases.append(("truncated NIfTI", [os.path.join(work, "short.nii")], "truncated"))
    # An unreachable URL (nothing listens on port 9 of loopback).
    cases.append(("unreachable URL", ["precomputed://http://127.0.0.1:9/none"], "cannot read"))
    # A 4D NIfTI.
    nib.save(nib.Nifti1Image(np.zeros((4, 4, 4, 2), np.uint8), np.eye(4)), os.path.join(work, "t.nii"))
    cases.append(("4D NIfTI", [os.path.join(work, "t.nii")], "4D"))
    for what, args, needle in cases:
        out = os.path.join(work, "bad.vod")
        r = run(isovox, "import", *args, "-o", out, ok=False)
        left = [f for f in os.listdir(work) if f.startswith("bad.vod")]
        if r.returncode == 0:
            failures.append(f"{what}: the import succeeded")
        elif needle not in r.stderr:
            failures.append(f"{what}: the error does not say {needle!r}: {r.stderr.strip()}")
        elif "panicked" in r.stderr:
            failures.append(f"{what}: panicked: {r.stderr.strip()}")
        elif left:
            failures.append(f"{what}: left {left} behind")
        else:
            print(f"{what}: refused ({r.stderr.strip().splitlines()[-1]})")


def exports(isovox, work, url, data, volume):
    """`isovox export --format zarr|precomputed` of a served volume reads back equal."""
    base = f"{url}/v1/volumes/{volume}"
    info = fetch_json(base)
    dtype = dtype_of(info)
    vod = os.path.join(data, f"{volume}.vod")
    zarr_dir = os.path.join(work, f"{volume}-export.zarr")
    pre_dir = os.path.join(work, f"{volume}-export-precomputed")
    run(isovox, "export", vod, "-o", zarr_dir, "--format", "zarr")
    run(isovox, "export", vod, "-o", pre_dir, "--format", "precomputed")
    r = run(isovox, "export", vod, "-o", zarr_dir, "--format", "zarr", ok=False)
    if r.returncode == 0 or "already exists" not in r.stderr:
        failures.append(f"export over an existing directory: {r.returncode} {r.stderr.strip()}")
    # The views themselves, imported over http: Isovox reading Isovox through the field's formats.
    shape = tuple(reversed(info["dims"]))
    truth = level_voxels(base, 0, dtype)
    for source in (f"zarr://{base}/zarr/", f"precomputed://{base}/precomputed"):
        got, _, _ = import_and_read(isovox, work, source, shape, dtype)
        same(f"import of {source}", got, truth)
    group = zarr.open_group(zarr_dir, mode="r")
    for k in range(len(info["levels"])):
        want = level_voxels(base, k, dtype)
        same(f"export zarr level {k} via zarr-python", group[str(k)][...], want)
        cv = CloudVolume(f"file://{pre_dir}", mip=k, progress=False)
        same(f"export precomputed level {k} via cloud-volume", np.asarray(cv[:, :, :])[..., 0].transpose(2, 1, 0), want)


if __name__ == "__main__":
    main()
