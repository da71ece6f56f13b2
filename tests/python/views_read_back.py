"""The field's clients read Isovox's views voxel for voxel, live and pinned to a version.

Against a real `isovox serve`: every level of each volume named, through tensorstore's `zarr3`
and `neuroglancer_precomputed` drivers, zarr-python, ome-zarr's reader and cloud-volume, must
equal `/levels/{k}?format=voxels`. Then an edit: the live views return the new voxels, the
views pinned to the old version the old ones (and the edit must have changed something, or the
comparison would prove nothing).

Usage: python views_read_back.py --url http://127.0.0.1:PORT --token TOKEN VOLUME...
"""

import argparse
import json
import sys
import urllib.request

import numpy as np
import tensorstore as ts
import zarr
from cloudvolume import CloudVolume
from ome_zarr.io import parse_url
from ome_zarr.reader import Label, Reader

from common import dtype_of, fetch_json, level_voxels


def tensorstore_zarr3(root, level):
    return ts.open({"driver": "zarr3", "kvstore": f"{root}/zarr/{level}/"}).result().read().result()


def tensorstore_precomputed(root, level):
    store = ts.open(
        {"driver": "neuroglancer_precomputed", "kvstore": f"{root}/precomputed/", "scale_index": level}
    ).result()
    # (x, y, z, channel) -> (z, y, x)
    return np.asarray(store.read().result())[..., 0].transpose(2, 1, 0)


def zarr_python(root, level):
    return zarr.open_group(f"{root}/zarr/", mode="r")[str(level)][...]


def cloud_volume(root, level):
    cv = CloudVolume(f"precomputed://{root}/precomputed", mip=level, progress=False, cache=False)
    return np.asarray(cv[:, :, :])[..., 0].transpose(2, 1, 0)


def ome_zarr(root, level):
    nodes = list(Reader(parse_url(f"{root}/zarr/"))())
    return np.asarray(nodes[0].data[level])


def tensorstore_segmentation(root, channel, level):
    store = ts.open(
        {"driver": "neuroglancer_precomputed", "kvstore": f"{root}/precomputed/{channel}/", "scale_index": level}
    ).result()
    return np.asarray(store.read().result())[..., 0].transpose(2, 1, 0)


def cloud_volume_segmentation(root, channel, level):
    cv = CloudVolume(f"precomputed://{root}/precomputed/{channel}", mip=level, progress=False, cache=False)
    return np.asarray(cv[:, :, :])[..., 0].transpose(2, 1, 0)


def tensorstore_zarr3_label(root, channel, level):
    return ts.open({"driver": "zarr3", "kvstore": f"{root}/zarr/labels/{channel}/{level}/"}).result().read().result()


def zarr_python_label(root, channel, level):
    return zarr.open_group(f"{root}/zarr/", mode="r")["labels"][channel][str(level)][...]


def ome_zarr_label(root, channel, level):
    nodes = list(Reader(parse_url(f"{root}/zarr/labels/{channel}/"))())
    # The reader also walks to the image and its other label images: take this channel's.
    label = next(n for n in nodes if n.load(Label) is not None and n.zarr.basename() == channel)
    return np.asarray(label.data[level])


# The attribute channels' data sources of the precomputed view: uint32 (uint64 for a u64
# channel) labels in the compressed_segmentation encoding, which both decode.
SEGMENTATION_CLIENTS = {
    "tensorstore neuroglancer_precomputed": tensorstore_segmentation,
    "cloud-volume": cloud_volume_segmentation,
}

# The OME-Zarr view's label images (labels/{channel}), in the channel's own type.
LABEL_CLIENTS = {
    "tensorstore zarr3": tensorstore_zarr3_label,
    "zarr-python": zarr_python_label,
    "ome-zarr": ome_zarr_label,
}


CLIENTS = {
    "tensorstore zarr3": tensorstore_zarr3,
    "tensorstore neuroglancer_precomputed": tensorstore_precomputed,
    "zarr-python": zarr_python,
    "ome-zarr": ome_zarr,
    "cloud-volume": cloud_volume,
}


def check(failures, what, got, want):
    if got.shape != want.shape or got.dtype != want.dtype:
        failures.append(f"{what}: {got.dtype}{got.shape}, expected {want.dtype}{want.shape}")
    elif not np.array_equal(got, want):
        diff = int(np.count_nonzero(got != want))
        failures.append(f"{what}: {diff} of {want.size} voxels differ")


def edit(base, token, info):
    """Carves an ellipsoid in the middle of the volume; returns the new version."""
    dims = info["dims"]
    body = json.dumps(
        {
            "op": "difference",
            "term": {
                "ellipsoid": {
                    "center": [d // 2 for d in dims],
                    "radii": [max(4, d // 4) for d in dims],
                }
            },
        }
    ).encode()
    request = urllib.request.Request(
        f"{base}/edits",
        data=body,
        method="POST",
        headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
    )
    with urllib.request.urlopen(request, timeout=60) as r:
        return json.load(r)["version"]


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--url", required=True)
    p.add_argument("--token", required=True)
    p.add_argument("volumes", nargs="+")
    a = p.parse_args()
    failures = []
    for name in a.volumes:
        base = f"{a.url}/v1/volumes/{name}"
        info = fetch_json(base)
        dtype = dtype_of(info)
        levels = len(info["levels"])
        before = [level_voxels(base, k, dtype) for k in range(levels)]
        for k in range(levels):
            for client, read in CLIENTS.items():
                check(failures, f"{name} level {k} via {client}", read(base, k), before[k])
        print(f"{name}: {levels} levels of {info['dims']} {info['voxel_type']} read back equal by {len(CLIENTS)} clients")
        for channel in info.get("channels", []):
            cname = channel["name"]
            dtype_c = {"u8": np.uint8, "u16": np.uint16, "u32": np.uint32, "u64": np.uint64}[channel["type"]]
            # compressed_segmentation holds uint32 or uint64: narrower channels widen to uint32.
            segmentation_dtype = np.uint64 if channel["type"] == "u64" else np.uint32
            for k in range(levels):
                want = level_voxels(base, k, dtype_c, channel=cname)
                if k == 0 and len(np.unique(want)) < 2:
                    failures.append(f"{name} channel {cname}: one value only; the check would prove little")
                for client, read in SEGMENTATION_CLIENTS.items():
                    check(failures, f"{name} channel {cname} level {k} via {client}", read(base, cname, k), want.astype(segmentation_dtype))
                for client, read in LABEL_CLIENTS.items():
                    check(failures, f"{name} label image {cname} level {k} via {client}", read(base, cname, k), want)
            colors = zarr.open_group(f"{base}/zarr/labels/{cname}/", mode="r").attrs["ome"]["image-label"]["colors"]
            palette = channel.get("palette", [])
            want_colors = [
                {"label-value": i, "rgba": [int(c[1:3], 16), int(c[3:5], 16), int(c[5:7], 16), 255]}
                for i, c in enumerate(palette)
            ]
            if colors != want_colors:
                failures.append(f"{name} label image {cname}: colours {colors}, expected {want_colors}")
            print(f"{name}: channel {cname}, {levels} levels read back equal as segmentations by {len(SEGMENTATION_CLIENTS)} clients and as label images by {len(LABEL_CLIENTS)}")

        old = info["version"]
        new = edit(base, a.token, info)
        after = [level_voxels(base, k, dtype) for k in range(levels)]
        changed = [k for k in range(levels) if not np.array_equal(before[k], after[k])]
        if not changed:
            failures.append(f"{name}: the edit changed no voxel; the pinning check would prove nothing")
        pinned_old = f"{base}/versions/{old}"
        pinned_new = f"{base}/versions/{new}"
        for k in range(levels):
            check(failures, f"{name} level {k} live zarr after the edit", tensorstore_zarr3(base, k), after[k])
            check(failures, f"{name} level {k} live precomputed after the edit", cloud_volume(base, k), after[k])
            check(failures, f"{name} level {k} pinned zarr v{old}", tensorstore_zarr3(pinned_old, k), before[k])
            check(failures, f"{name} level {k} pinned zarr v{old} (zarr-python)", zarr_python(pinned_old, k), before[k])
            check(failures, f"{name} level {k} pinned precomputed v{old}", tensorstore_precomputed(pinned_old, k), before[k])
            check(failures, f"{name} level {k} pinned precomputed v{old} (cloud-volume)", cloud_volume(pinned_old, k), before[k])
            check(failures, f"{name} level {k} pinned zarr v{new}", tensorstore_zarr3(pinned_new, k), after[k])
        print(f"{name}: after the edit to version {new} (levels {changed} changed), live views show it and version {old} stays pinned")
    if failures:
        sys.exit("\n".join(failures))
    print("every client read every level equal, live and pinned")


if __name__ == "__main__":
    main()
