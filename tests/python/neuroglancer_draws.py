"""Neuroglancer (the client bundled in PyPI's `neuroglancer` package, served by its own Python
side) in headless Chromium draws a volume from the precomputed view and from the Zarr view.

The check is by pixels: the xy cross-section at a known position and zoom (one voxel per screen
pixel) must agree with the volume's voxels there, read through `/levels/0?format=voxels`: a
pixel is bright exactly where its voxel is at least the surface value, for at least 98% of the
slice (the rest is the one-voxel rim where linear sampling blends both sides). The screenshot is
retaken until it agrees or 90 s pass, since Neuroglancer draws coarse levels first.

The volume's material channel, opened from the precomputed view's `material/` source (uint32
labels in the compressed_segmentation encoding) as a segmentation layer, must be drawn in more
than one colour, each material's voxels in a colour of their own: for each material covering at
least 0.5% of the slice, at least 90% of its pixels are within 12 levels of their median colour,
and the medians of any two of them differ.

Isovox's own viewer links to Neuroglancer ("Open in Neuroglancer"): the state in that link,
read from the page and given to the same client, must show the volume's precomputed source at
the link's position, and drawn there (the same pixel check) it must agree with the voxels.

Usage: python neuroglancer_draws.py --url http://127.0.0.1:PORT --volume demo --out DIR
"""

import argparse
import contextlib
import io
import json
import urllib.parse
import os
import subprocess
import sys
import time

import neuroglancer
import numpy as np
from PIL import Image

from common import fetch_json, level_voxels

WIDTH, HEIGHT = 640, 400
SHADER = "void main() { emitGrayscale(toNormalized(getDataValue())); }"
AGREEMENT = 0.98


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--url", required=True)
    p.add_argument("--volume", default="demo")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    base = f"{a.url}/v1/volumes/{a.volume}"
    info = fetch_json(base)
    dx, dy, dz = info["dims"]
    if info["voxel_type"] != "u8":
        sys.exit(f"the demo volume should be u8, it is {info['voxel_type']}")
    z = dz // 2
    # The slice the viewer is expected to draw: a window of at most WIDTH x HEIGHT voxels
    # around the centre of plane z.
    wx, wy = min(dx, WIDTH - 40), min(dy, HEIGHT - 40)
    x0, y0 = (dx - wx) // 2, (dy - wy) // 2
    truth = level_voxels(base, 0, np.uint8, (x0, y0, z, x0 + wx, y0 + wy, z + 1))[0]
    inside = truth >= 127
    if not (0.2 < inside.mean() < 0.8):
        sys.exit(f"the slice should hold both solid and empty voxels, {inside.mean():.2f} is solid")

    neuroglancer.set_server_bind_address("127.0.0.1")
    failures = []
    for view, source in [
        ("precomputed", f"precomputed://{base}/precomputed"),
        ("zarr", f"zarr3://{base}/zarr/"),
    ]:
        agreement = draw(view, source, (x0, y0, z), (wx, wy), inside, a.out)
        print(f"{view}: {agreement:.4f} of the slice's pixels agree with its voxels")
        if agreement < AGREEMENT:
            failures.append(f"{view}: only {agreement:.4f} of the pixels agree (needs {AGREEMENT})")
    ok, why = draw_from_viewer_link(a.url, a.volume, base, a.out)
    print(f"viewer link: {why}")
    if not ok:
        failures.append(f"viewer link: {why}")

    channels = [c["name"] for c in info.get("channels", [])]
    if "material" not in channels:
        failures.append(f"the demo volume should have a material channel, it has {channels}")
    else:
        labels = level_voxels(base, 0, np.uint8, (x0, y0, z, x0 + wx, y0 + wy, z + 1), channel="material")[0]
        ok, why = draw_segmentation(f"precomputed://{base}/precomputed/material", (x0, y0, z), (wx, wy), labels, a.out)
        print(f"segmentation: {why}")
        if not ok:
            failures.append(f"segmentation: {why}")
    if failures:
        sys.exit("; ".join(failures))
    print("neuroglancer draws the volume from both views, and its materials as a segmentation")


def plain_xy(s):
    """An xy cross-section with nothing drawn over the data."""
    s.layout = "xy"
    s.show_axis_lines = False
    s.show_scale_bar = False
    s.show_default_annotations = False


def showing(name, layer):
    """Sets a viewer to show `layer` as `name` in a plain xy cross-section."""
    def configure(viewer):
        with viewer.txn() as s:
            s.layers[name] = layer
            plain_xy(s)
    return configure


@contextlib.contextmanager
def opened(configure):
    """A Neuroglancer viewer set up by `configure(viewer)`, open in chromium; yields (viewer, its
    dimension names) once the browser has read the layers' metadata."""
    viewer = neuroglancer.Viewer()
    configure(viewer)
    browser = subprocess.Popen(
        ["node", os.path.join(os.path.dirname(__file__), "open_page.mjs"),
         viewer.get_viewer_url(), str(WIDTH), str(HEIGHT)],
        stdin=subprocess.PIPE,
    )
    try:
        # The layer's coordinate space arrives once the browser has read the metadata.
        deadline = time.time() + 60
        while not viewer.state.dimensions.names and time.time() < deadline:
            time.sleep(0.2)
        yield viewer, list(viewer.state.dimensions.names)
    finally:
        browser.stdin.close()
        try:
            browser.wait(timeout=30)
        except subprocess.TimeoutExpired:
            browser.kill()


def draw(view, source, origin, size, inside, out_dir):
    with opened(showing("volume", neuroglancer.ImageLayer(source=source, shader=SHADER))) as (viewer, names):
        if sorted(names) != ["x", "y", "z"]:
            return fail(view, f"the viewer's dimensions are {names}, not x, y, z")
        (x0, y0, z), (wx, wy) = origin, size
        # The centre of the window; the precomputed view puts voxel i at [i, i+1), the
        # OME-Zarr view centres it on i.
        shift = 0.0 if view == "precomputed" else -0.5
        centre = {"x": x0 + wx / 2 + shift, "y": y0 + wy / 2 + shift, "z": z + 0.5 + shift}
        with viewer.txn() as s:
            s.display_dimensions = ["x", "y", "z"]
            s.position = [centre[n] for n in names]
            s.cross_section_scale = 1
        return agreement(viewer, inside, os.path.join(out_dir, f"neuroglancer-{view}.png"))


def agreement(viewer, inside, shot_path):
    """The best share of the drawn window's pixels that are bright exactly where `inside` is
    (indexed [y, x]; the window centred on the canvas, one voxel per pixel), retaking the
    screenshot until it reaches AGREEMENT or 90 s pass (Neuroglancer draws coarse levels first).
    The last screenshot is saved at `shot_path`."""
    wy, wx = inside.shape
    best, image = 0.0, None
    deadline = time.time() + 90
    while time.time() < deadline:
        shot = viewer.screenshot(size=[WIDTH, HEIGHT])
        image = Image.open(io.BytesIO(shot.screenshot.image)).convert("L")
        left, top = (WIDTH - wx) // 2, (HEIGHT - wy) // 2
        bright = np.asarray(image)[top:top + wy, left:left + wx] >= 127
        best = max(best, float((bright == inside).mean()))
        if best >= AGREEMENT:
            break
        time.sleep(1)
    if image is not None:
        image.save(shot_path)
    return best


def draw_from_viewer_link(url, volume, base, out_dir):
    """Reads the viewer page's Neuroglancer link, gives its state to the client, and checks the
    layer and position it shows, then the slice drawn there. Returns (agrees, why)."""
    href = subprocess.run(
        ["node", os.path.join(os.path.dirname(__file__), "viewer_link.mjs"), url, volume],
        capture_output=True, text=True, timeout=120, check=True,
    ).stdout.strip()
    state = json.loads(urllib.parse.unquote(href[href.index("#!") + 2:]))
    source = state["layers"][0]["source"]
    if source != f"precomputed://{base}/precomputed":
        return False, f"the link's source is {source}"
    center = state["navigation"]["pose"]["position"]["voxelCoordinates"]
    with opened(lambda viewer: viewer.set_state(neuroglancer.ViewerState(state))) as (viewer, names):
        if sorted(names) != ["x", "y", "z"]:
            return False, f"the viewer's dimensions are {names}, not x, y, z"
        position = dict(zip(names, viewer.state.position))
        # Precomputed puts voxel i at [i, i + 1): the link's voxel coordinates as they are.
        if any(abs(position[n] - c) > 0.5 for n, c in zip("xyz", center)):
            return False, f"the client is at {position}, the link says {center}"
        layers = [layer.name for layer in viewer.state.layers]
        # Drawn at the link's position, one voxel per pixel, as draw() checks.
        x, y, z = (int(c) for c in center)
        info = fetch_json(base)
        wx, wy = min(info["dims"][0], WIDTH - 40), min(info["dims"][1], HEIGHT - 40)
        x0 = min(max(0, x - wx // 2), info["dims"][0] - wx)
        y0 = min(max(0, y - wy // 2), info["dims"][1] - wy)
        truth = level_voxels(base, 0, np.uint8, (x0, y0, z, x0 + wx, y0 + wy, z + 1))[0] >= 127
        with viewer.txn() as s:
            s.layers[layers[0]].shader = SHADER
            plain_xy(s)
            s.position = [{"x": x0 + wx / 2, "y": y0 + wy / 2, "z": z + 0.5}[n] for n in names]
            s.cross_section_scale = 1
        best = agreement(viewer, truth, os.path.join(out_dir, "neuroglancer-link.png"))
        why = f"layer {layers} at {center} from the viewer's link; {best:.4f} of the slice's pixels agree"
        return best >= AGREEMENT, why


def draw_segmentation(source, origin, size, labels, out_dir):
    """Draws `source` as a segmentation layer over the window `origin`, `size` of plane z; `labels`
    (indexed [y, x]) are its values there. Returns (agrees, why)."""
    ids = [int(i) for i in np.unique(labels) if i != 0 and (labels == i).mean() >= 0.005]
    if len(ids) < 2:
        return False, f"the slice should hold two materials or more on 0.5% of it, it holds {ids}"
    layer = neuroglancer.SegmentationLayer(source=source, segments=ids, selected_alpha=1.0)
    with opened(showing("material", layer)) as (viewer, names):
        if sorted(names) != ["x", "y", "z"]:
            return False, f"the viewer's dimensions are {names}, not x, y, z"
        (x0, y0, z), (wx, wy) = origin, size
        centre = {"x": x0 + wx / 2, "y": y0 + wy / 2, "z": z + 0.5}
        with viewer.txn() as s:
            s.display_dimensions = ["x", "y", "z"]
            s.position = [centre[n] for n in names]
            s.cross_section_scale = 1
        why, image = "no screenshot", None
        deadline = time.time() + 90
        while time.time() < deadline:
            shot = viewer.screenshot(size=[WIDTH, HEIGHT])
            image = Image.open(io.BytesIO(shot.screenshot.image)).convert("RGB")
            pixels = np.asarray(image).astype(int)
            left, top = (WIDTH - wx) // 2, (HEIGHT - wy) // 2
            window = pixels[top:top + wy, left:left + wx]
            medians, agree = {}, True
            for i in ids:
                mine = window[labels == i]
                median = np.median(mine, axis=0)
                near = (np.abs(mine - median).max(axis=1) <= 12).mean()
                medians[i] = median
                if near < 0.9 or median.max() < 30:
                    agree, why = False, f"material {i}: {near:.2f} of its pixels near its colour {median.tolist()}"
                    break
            if agree:
                same = [(i, j) for i in ids for j in ids if i < j and np.abs(medians[i] - medians[j]).max() <= 12]
                if same:
                    agree, why = False, f"materials {same} are drawn in the same colour"
                else:
                    why = f"{len(ids)} materials {ids} drawn in {len(ids)} colours " + str({i: medians[i].tolist() for i in ids})
                    break
            time.sleep(1)
        if image is not None:
            image.save(os.path.join(out_dir, "neuroglancer-segmentation.png"))
        return agree, why


def fail(view, why):
    print(f"{view}: {why}", file=sys.stderr)
    return 0.0


if __name__ == "__main__":
    main()
