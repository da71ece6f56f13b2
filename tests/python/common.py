"""What the formats tests share: reading a volume's truth from Isovox's own API."""

import json
import urllib.request

import numpy as np


def fetch_json(url):
    with urllib.request.urlopen(url, timeout=60) as r:
        return json.load(r)


def fetch(url, headers=None):
    request = urllib.request.Request(url, headers=headers or {})
    with urllib.request.urlopen(request, timeout=60) as r:
        return r.status, dict(r.headers), r.read()


def level_voxels(base, level, dtype, region=None, channel=None):
    """Level `level` of the volume at `base` (`.../v1/volumes/NAME`) as an array indexed
    [z, y, x], from `/levels/{level}?format=voxels` (x fastest, little endian). `region` is
    (x0, y0, z0, x1, y1, z1), max exclusive; `channel` names an attribute channel to read
    instead of density."""
    url = f"{base}/levels/{level}?format=voxels"
    if channel is not None:
        url += f"&channel={channel}"
    if region is None:
        info = fetch_json(base)
        dims = info["levels"][level]["dims"]
        region = (0, 0, 0, *dims)
    else:
        url += "&region=" + ",".join(str(v) for v in region)
    x0, y0, z0, x1, y1, z1 = region
    _, _, body = fetch(url)
    return np.frombuffer(body, dtype=np.dtype(dtype).newbyteorder("<")).reshape(
        z1 - z0, y1 - y0, x1 - x0
    )


def dtype_of(info):
    return {"u8": np.uint8, "u16": np.uint16}[info["voxel_type"]]
