"""Render meshes side by side to one PNG, headless: flat-shaded faces drawn back to front.

    render.py OUT.png [--view az,el] [--size W] [--crop x0,y0,x1,y1] LABEL=MESH.obj ...

Every panel shares the first mesh's framing (the same centre and scale), so the panels can be
compared pixel by pixel. Faces are shaded by their normal against a fixed head light, which
shows noise and creases the way a mesh viewer's flat shading does. Used by
scripts/render.sh (which installs numpy and pillow into target/render-tools/).
"""

import argparse
import math
import sys

import numpy as np
from PIL import Image, ImageDraw, ImageFont


def read_obj(path):
    vertices, faces = [], []
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            if line.startswith("v "):
                vertices.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                ids = [int(tok.split("/")[0]) for tok in line.split()[1:]]
                ids = [i - 1 if i > 0 else len(vertices) + i for i in ids]
                for k in range(1, len(ids) - 1):
                    faces.append([ids[0], ids[k], ids[k + 1]])
    return np.asarray(vertices, dtype=float), np.asarray(faces, dtype=np.int64)


def rotation(azimuth, elevation):
    a, e = math.radians(azimuth), math.radians(elevation)
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, math.cos(e), -math.sin(e)], [0, math.sin(e), math.cos(e)]])
    return rx @ rz


def draw(vertices, faces, frame, size, crop):
    centre, scale, rot = frame
    p = (vertices - centre) @ rot.T * scale
    tri = p[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    lengths[lengths == 0] = 1
    normals /= lengths[:, None]
    # Camera looks down -z; a face seen from behind is shaded by its back (open scans).
    light = np.array([0.3, 0.4, 1.0])
    light /= np.linalg.norm(light)
    shade = np.abs(normals @ light)
    order = np.argsort(tri[:, :, 2].mean(axis=1))
    image = Image.new("RGB", (size, size), (255, 255, 255))
    pen = ImageDraw.Draw(image)
    half = size / 2
    for i in order:
        t = tri[i]
        g = int(40 + 200 * shade[i])
        colour = (g, int(g * 0.96), int(g * 0.9))
        xy = [(half + x, half - y) for x, y, _ in t]
        pen.polygon(xy, fill=colour, outline=colour)
    if crop:
        x0, y0, x1, y1 = crop
        image = image.crop((int(x0 * size), int(y0 * size), int(x1 * size), int(y1 * size)))
    return image


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("panels", nargs="+", help="LABEL=PATH.obj")
    ap.add_argument("--view", default="0,-60", help="azimuth,elevation in degrees")
    ap.add_argument("--size", type=int, default=520)
    ap.add_argument("--crop", default=None, help="x0,y0,x1,y1 as fractions of the panel")
    args = ap.parse_args()
    azimuth, elevation = (float(x) for x in args.view.split(","))
    crop = [float(x) for x in args.crop.split(",")] if args.crop else None
    meshes = []
    for panel in args.panels:
        label, _, path = panel.partition("=")
        meshes.append((label, *read_obj(path)))
    _, v0, _ = meshes[0]
    rot = rotation(azimuth, elevation)
    centre = (v0.max(axis=0) + v0.min(axis=0)) / 2
    extent = np.abs((v0 - centre) @ rot.T)[:, :2].max()
    frame = (centre, 0.47 * args.size / extent, rot)
    images = [draw(v, f, frame, args.size, crop) for _, v, f in meshes]
    w, h = images[0].size
    sheet = Image.new("RGB", (w * len(images), h + 28), (255, 255, 255))
    pen = ImageDraw.Draw(sheet)
    font = ImageFont.load_default()
    for k, ((label, _, _), im) in enumerate(zip(meshes, images)):
        sheet.paste(im, (k * w, 28))
        pen.text((k * w + 8, 6), label, fill=(0, 0, 0), font=font)
    sheet.save(args.out, optimize=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
