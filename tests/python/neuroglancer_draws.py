"""Neuroglancer (the client bundled in PyPI's `neuroglancer` package, served by its own Python
side) in headless Chromium draws a volume from the precomputed view and from the Zarr view.

The check is by pixels: the xy cross-section at a known position and zoom (one voxel per screen
pixel) must agree with the volume's voxels there, read through `/levels/0?format=voxels`: a
pixel is bright exactly where its voxel is at least the surface value, for at least 98% of the
slice (the rest is the one-voxel rim where linear sampling blends both sides). The screenshot is
retaken until it agrees or 90 s pass, since Neuroglancer draws coarse levels first.

Usage: python neuroglancer_draws.py --url http://127.0.0.1:PORT --volume demo --out DIR
"""

import argparse
import io
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
    if failures:
        sys.exit("; ".join(failures))
    print("neuroglancer draws the volume from both views")


def draw(view, source, origin, size, inside, out_dir):
    viewer = neuroglancer.Viewer()
    with viewer.txn() as s:
        s.layers["volume"] = neuroglancer.ImageLayer(source=source, shader=SHADER)
        s.layout = "xy"
        s.show_axis_lines = False
        s.show_scale_bar = False
        s.show_default_annotations = False
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
        names = list(viewer.state.dimensions.names)
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
        best, image = 0.0, None
        deadline = time.time() + 90
        while time.time() < deadline:
            shot = viewer.screenshot(size=[WIDTH, HEIGHT])
            image = Image.open(io.BytesIO(shot.screenshot.image)).convert("L")
            pixels = np.asarray(image)
            # The window is centred on the canvas, one voxel per pixel.
            left, top = (WIDTH - wx) // 2, (HEIGHT - wy) // 2
            bright = pixels[top:top + wy, left:left + wx] >= 127
            best = max(best, float((bright == inside).mean()))
            if best >= AGREEMENT:
                break
            time.sleep(1)
        if image is not None:
            image.save(os.path.join(out_dir, f"neuroglancer-{view}.png"))
        return best
    finally:
        browser.stdin.close()
        try:
            browser.wait(timeout=30)
        except subprocess.TimeoutExpired:
            browser.kill()


def fail(view, why):
    print(f"{view}: {why}", file=sys.stderr)
    return 0.0


if __name__ == "__main__":
    main()
