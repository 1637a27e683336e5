"""Seeds a running `radiance serve` for .ci/schemathesis, with the standard library only.

Uploads two copies of a tiny generated Blender scene (a sphere seen from 8 training
and 2 test cameras, 16x16 RGBA), trains one 4-step nerf-tiny job on the first and
waits for its model, renders a 4-frame 16x16 GIF orbit of it, then prints schemathesis
configuration (TOML) that feeds those ids to the operations taking an id (mixed with
generated ids). DELETE deletes, so it gets spares of its own and the seeded records stay
for GET: the second scene, spare models and videos, and finished jobs (queued jobs
canceled at once, cheap to make in numbers).

Usage: schemathesis_seed.py BASE_URL >>schemathesis.toml

"""

import io
import json
import math
import struct
import sys
import time
import urllib.error
import urllib.request
import zipfile
import zlib

SIZE, FOV = 16, 0.7


def png(w, h, rgba):
    rows = b"".join(b"\x00" + bytes(rgba[y * w * 4 : (y + 1) * w * 4]) for y in range(h))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b"")


def norm(v):
    n = math.sqrt(sum(x * x for x in v))
    return [x / n for x in v]


def cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def camera(azimuth, elevation, radius=4.0):
    """Camera-to-world (OpenGL: looks down -z, y up) at an orbit position around the origin, z up."""
    az, el = math.radians(azimuth), math.radians(elevation)
    eye = [radius * math.cos(el) * math.cos(az), radius * math.cos(el) * math.sin(az), radius * math.sin(el)]
    z = norm(eye)  # backwards
    x = norm(cross([0.0, 0.0, 1.0], z))
    y = cross(z, x)
    return [[x[i], y[i], z[i], eye[i]] for i in range(3)] + [[0.0, 0.0, 0.0, 1.0]]


def view(c2w):
    """A unit sphere at the origin, shaded by its normal, on a transparent background."""
    f = 0.5 * SIZE / math.tan(0.5 * FOV)
    eye = [c2w[i][3] for i in range(3)]
    out = []
    for j in range(SIZE):
        for i in range(SIZE):
            d = [(i + 0.5 - SIZE / 2) / f, -(j + 0.5 - SIZE / 2) / f, -1.0]
            d = norm([sum(c2w[r][k] * d[k] for k in range(3)) for r in range(3)])
            b = sum(e * dd for e, dd in zip(eye, d))
            disc = b * b - (sum(e * e for e in eye) - 1.0)
            if disc < 0:
                out += [0, 0, 0, 0]
                continue
            t = -b - math.sqrt(disc)
            n = [e + t * dd for e, dd in zip(eye, d)]
            out += [int(255 * (0.5 + 0.5 * c)) for c in n] + [255]
    return png(SIZE, SIZE, out)


def scene_zip():
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        splits = {"train": [(45.0 * k, 30.0) for k in range(8)], "test": [(22.5 + 90.0 * k, 20.0) for k in range(2)]}
        for split, poses in splits.items():
            frames = []
            for k, (az, el) in enumerate(poses):
                c2w = camera(az, el)
                z.writestr(f"{split}/r_{k}.png", view(c2w))
                frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": c2w})
            doc = {"camera_angle_x": FOV, "near": 2.0, "far": 6.0, "frames": frames}
            z.writestr(f"transforms_{split}.json", json.dumps(doc))
    return buf.getvalue()


def call(base, method, path, body=None, content_type="application/json"):
    data = json.dumps(body).encode() if content_type == "application/json" and body is not None else body
    req = urllib.request.Request(base + path, data=data, method=method)
    if data is not None:
        req.add_header("Content-Type", content_type)
    with urllib.request.urlopen(req, timeout=60) as r:
        return json.load(r)


FINAL = ("succeeded", "failed", "canceled")


def wait(base, job, want="succeeded", key=None):
    """Waits for a job to end; returns the job (exits unless it ended `want` with `key` set)."""
    deadline = time.time() + 120
    while True:
        j = call(base, "GET", f"/v1/jobs/{job}")
        if j["status"] in FINAL:
            break
        if time.time() > deadline:
            sys.exit(f"seed job {job} did not finish in 120 s: {j}")
        time.sleep(0.2)
    if want and (j["status"] != want or (key and not j.get(key))):
        sys.exit(f"seed job {job} did not end {want} with {key}: {j}")
    return j


def train(base, scene):
    """A 4-step nerf-tiny job; returns (job id, model id)."""
    body = {"scene_id": scene, "model": "nerf-tiny", "budget": {"steps": 4}, "seed": 0, "batch_rays": 64}
    job = call(base, "POST", "/v1/jobs", body)["id"]
    return job, wait(base, job, key="model_id")["model_id"]


def video(base, model):
    """A 4-frame 16x16 GIF orbit of a model; returns its video id."""
    body = {"frames": 4, "fps": 4, "width": 16, "height": 16, "format": "gif"}
    return wait(base, call(base, "POST", f"/v1/models/{model}/videos", body)["id"], key="video_id")["video_id"]


def canceled_jobs(base, scene, n):
    """`n` jobs canceled (mostly while still queued); returns their ids once all have ended."""
    body = {"scene_id": scene, "model": "nerf-tiny", "budget": {"steps": 1}, "seed": 0, "batch_rays": 64}
    jobs = [call(base, "POST", "/v1/jobs", body)["id"] for _ in range(n)]
    for job in jobs:
        try:
            call(base, "POST", f"/v1/jobs/{job}/cancel", {})
        except urllib.error.HTTPError as e:  # 409: it ended before the cancel
            if e.code != 409:
                raise
    for job in jobs:
        wait(base, job, want=None)
    return jobs


def main():
    base = sys.argv[1]
    archive = scene_zip()
    scenes = [call(base, "POST", "/v1/scenes", archive, "application/zip")["id"] for _ in range(2)]
    job, model = train(base, scenes[0])
    vid = video(base, model)
    spare_trained = [train(base, scenes[0]) for _ in range(3)]
    spare_videos = [video(base, model) for _ in range(3)]
    spare_jobs = canceled_jobs(base, scenes[0], 20) + [j for j, _ in spare_trained]
    ids = {
        "scene": [scenes[0]],
        "spare_scene": [scenes[1]],
        "job": [job],
        "spare_job": spare_jobs,
        "model": [model],
        "spare_model": [m for _, m in spare_trained],
        "video": [vid],
        "spare_video": spare_videos,
    }
    # Regexes over operation names ("GET /v1/scenes/{id}"): one [[operations]] entry's
    # include-method-regex and include-path-regex would select either, not both.
    bindings = [
        ("GET", "/v1/scenes/\\{id\\}$", "scene"),
        ("DELETE", "/v1/scenes/\\{id\\}$", "spare_scene"),
        ("GET|POST", "/v1/jobs/\\{id\\}", "job"),
        ("DELETE", "/v1/jobs/\\{id\\}$", "spare_job"),
        ("GET|POST", "/v1/models/\\{id\\}", "model"),
        ("DELETE", "/v1/models/\\{id\\}$", "spare_model"),
        ("GET", "/v1/videos/\\{id\\}$", "video"),
        ("DELETE", "/v1/videos/\\{id\\}$", "spare_video"),
    ]
    out = [f"\n# Seeded by schemathesis_seed.py: {ids}\n"]
    out += [f"[dictionaries.{name}]\nvalues = {json.dumps(values)}\n" for name, values in ids.items()]
    for method, path, name in bindings:
        entry = f"[[operations]]\ninclude-name-regex = '^({method}) {path}'\n"
        if method == "DELETE":
            # Only spares: elsewhere one id in five is generated or taken from earlier responses
            # (schemathesis' resource pool, also used by the coverage phase), and from DELETE that
            # would delete the records the other operations are fed.
            entry += 'parameters = { "path.id" = { dictionary = "%s", probability = 1.0 } }\n' % name
            for phase in ("examples", "coverage", "fuzzing"):
                entry += f"phases.{phase}.extra-data-sources.responses = false\n"
        else:
            entry += 'parameters = { "path.id" = { dictionary = "%s", probability = 0.8 } }\n' % name
        out.append(entry)
    print("\n".join(out))
    print(f"seeded: {ids}", file=sys.stderr)


if __name__ == "__main__":
    main()
