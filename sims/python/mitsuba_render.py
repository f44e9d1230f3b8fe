"""The simulator's Mitsuba 3 backend, Python side.

Loads a scene that `sims::render::mitsuba` exported (scene.json, PLY meshes, raw float32
texture arrays) and answers render requests over stdin/stdout until stdin closes. The
rays come from the Rust side (the sensors' exact per-pixel rays: ray tables, any
distortion, any principal point), so no Mitsuba camera model is involved.

Protocol (numbers little-endian):
  start-up   one JSON line: {"ready": true, ...} or {"ready": false, "error": "..."}
  request    one JSON line {"op": "echoes" | "radiance", "n": N, ...}, then N x 6
             float32: each ray's origin xyz and unit direction xyz (scene coordinates)
  reply      one JSON line {"ok": true, "floats": F}, then F float32; or
             {"ok": false, "error": "..."}
  echoes     per ray: distance (NaN = no hit), |cos incidence|, shape index, albedo rgb
  radiance   per ray: linear rgb = path-traced light (max_depth, spp) + ambient x albedo
             at the first hit; the background where the ray hits nothing

Usage: python mitsuba_render.py SCENE_DIR  (DRJIT_LIBLLVM_PATH names libLLVM)
"""

import json
import os
import sys
import traceback

# The protocol owns the real stdout; anything Mitsuba prints goes to stderr.
PROTO = os.fdopen(os.dup(1), "wb")
os.dup2(2, 1)

VARIANT = "llvm_ad_rgb"

# Imported in main(), so that a failed import is reported on the protocol.
mi = dr = np = None


def reply(header, payload=None):
    PROTO.write((json.dumps(header) + "\n").encode())
    if payload is not None:
        PROTO.write(payload)
    PROTO.flush()


def aligned_f32(count):
    """A float32 array of `count` values whose data starts on a 64-byte boundary:
    Dr.Jit maps numpy memory directly, and kernels are specialised (and recompiled) on
    the alignment of their inputs."""
    buf = np.empty(count + 16, np.float32)
    off = (-buf.ctypes.data % 64) // 4
    return buf[off : off + count]


def as_float(values):
    out = aligned_f32(values.size)
    out[:] = values
    return mi.Float(out)


class Renderer:
    def __init__(self, scene_dir):
        self.dir = scene_dir
        with open(os.path.join(scene_dir, "scene.json")) as f:
            self.spec = json.load(f)
        if self.spec.get("version") != 1:
            raise ValueError(f"scene.json version {self.spec.get('version')} (expected 1)")
        self.bitmaps = {}
        self.scenes = {}
        self.integrators = {}
        self.ambient = mi.Color3f(*self.spec["ambient"])
        self.background = mi.Color3f(*self.spec["background"])
        self.scene(None)

    # --- scene ----------------------------------------------------------------

    def bitmap(self, tex):
        key = tex["file"]
        if key not in self.bitmaps:
            data = np.fromfile(os.path.join(self.dir, key), dtype="<f4")
            w, h = tex["width"], tex["height"]
            if data.size != w * h * 3:
                raise ValueError(f"{key}: {data.size} floats, expected {w}x{h}x3")
            self.bitmaps[key] = mi.Bitmap(data.reshape(h, w, 3))
        return self.bitmaps[key]

    def reflectance(self, albedo):
        if "rgb" in albedo:
            return {"type": "rgb", "value": albedo["rgb"]}
        m = albedo["to_uv"]
        return {
            "type": "bitmap",
            "bitmap": self.bitmap(albedo),
            "raw": True,
            "filter_type": albedo["filter"],
            "wrap_mode": albedo["wrap"],
            "to_uv": mi.ScalarTransform3f([m[0:3], m[3:6], m[6:9]]),
        }

    def bsdf(self, spec, specular_scale):
        """Two-sided Lambertian; with a specular scale, materials with a specular
        reflectance become `roughplastic` (Beckmann roughness from the Blinn-Phong
        exponent)."""
        refl = self.reflectance(spec["albedo"])
        k_s = spec.get("specular", 0.0) * (specular_scale or 0.0)
        if k_s > 0.0:
            inner = {
                "type": "roughplastic",
                "distribution": "beckmann",
                "alpha": spec["alpha"],
                "diffuse_reflectance": refl,
                "specular_reflectance": {"type": "rgb", "value": [k_s] * 3},
                "nonlinear": False,
            }
        else:
            inner = {"type": "diffuse", "reflectance": refl}
        return {"type": "twosided", "inner": inner}

    def scene(self, specular_scale):
        """The Mitsuba scene (and shape lookup table) for a specular scale (None:
        Lambertian only), loaded on first use."""
        key = specular_scale
        if key in self.scenes:
            return self.scenes[key]
        d = {"type": "scene"}
        shapes = []
        bsdfs = self.spec["bsdfs"]
        for i, shape in enumerate(self.spec["shapes"]):
            kind = shape["kind"]
            entry = {"bsdf": self.bsdf(bsdfs[shape["bsdf"]], specular_scale)}
            if kind == "mesh":
                entry.update(
                    type="ply",
                    filename=os.path.join(self.dir, shape["file"]),
                    face_normals=True,
                )
            else:
                m = shape["to_world"]
                entry.update(
                    type=kind,
                    to_world=mi.ScalarTransform4f([m[0:4], m[4:8], m[8:12], m[12:16]]),
                )
            obj = mi.load_dict(entry)
            shapes.append((i, obj))
            d[f"s{i:07d}"] = obj
        for k, light in enumerate(self.spec["lights"]):
            if light["kind"] == "directional":
                d[f"light{k}"] = {
                    "type": "directional",
                    "direction": light["direction"],
                    "irradiance": {"type": "rgb", "value": light["irradiance"]},
                }
            else:
                d[f"light{k}"] = {
                    "type": "point",
                    "position": light["position"],
                    "intensity": {"type": "rgb", "value": light["intensity"]},
                }
        scene = mi.load_dict(d)
        # Shape pointers are registry ids: a table from id to the exported index.
        ids = [
            (int(np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(obj)))[0]), i)
            for i, obj in shapes
        ]
        lut = np.full(max((r for r, _ in ids), default=0) + 1, 0xFFFFFFFF, dtype=np.uint32)
        for reg, index in ids:
            lut[reg] = index
        self.scenes[key] = (scene, mi.UInt32(lut))
        return self.scenes[key]

    def integrator(self, max_depth):
        if max_depth not in self.integrators:
            self.integrators[max_depth] = mi.load_dict(
                {"type": "path", "max_depth": int(max_depth), "hide_emitters": True}
            )
        return self.integrators[max_depth]

    # --- requests -------------------------------------------------------------

    def rays(self, rays, n):
        o = mi.Point3f(*(as_float(rays[:, k]) for k in range(3)))
        d = mi.Vector3f(*(as_float(rays[:, k]) for k in range(3, 6)))
        return o, d

    def echoes(self, req, rays):
        n = req["n"]
        scene, lut = self.scene(None)
        o, d = self.rays(rays, n)
        ray = mi.Ray3f(o, d)
        si = scene.ray_intersect(ray)
        valid = si.is_valid()
        t = dr.select(valid, si.t, dr.nan)
        cos = dr.select(valid, dr.abs(dr.dot(si.n, d)), 0.0)
        albedo = si.bsdf(ray).eval_diffuse_reflectance(si, valid)
        reg = dr.reinterpret_array(mi.UInt32, si.shape)
        index = dr.gather(mi.UInt32, lut, reg, valid & (reg < dr.width(lut)))
        out = np.empty((n, 6), np.float32)
        out[:, 0] = np.array(t)
        out[:, 1] = np.array(cos)
        out[:, 2] = np.array(mi.Float(index))
        out[:, 3:6] = np.array(albedo).T
        return out

    def radiance(self, req, rays):
        n = req["n"]
        spp = max(1, int(req.get("spp", 1)))
        specular = req.get("specular")
        scene, _ = self.scene(float(specular) if specular else None)
        integrator = self.integrator(max(1, int(req.get("max_depth", 2))))
        o, d = self.rays(rays, n)
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(mi.UInt32(int(req.get("seed", 0)) & 0xFFFFFFFF), n)
        acc = mi.Color3f(0.0)
        for _ in range(spp):
            light, _, _ = integrator.sample(scene, sampler, mi.RayDifferential3f(o, d))
            acc += light
            sampler.advance()
            # Evaluate the sampler's state with the sum: otherwise every sample
            # would recompute the random numbers of all samples before it.
            sampler.schedule_state()
            dr.eval(acc)
        ray = mi.Ray3f(o, d)
        si = scene.ray_intersect(ray)
        valid = si.is_valid()
        albedo = si.bsdf(ray).eval_diffuse_reflectance(si, valid)
        rgb = dr.select(valid, acc / spp + self.ambient * albedo, self.background)
        return np.ascontiguousarray(np.array(rgb).T, dtype=np.float32)


def read_exact(stream, buf):
    view = memoryview(buf).cast("B")
    got = 0
    while got < len(view):
        k = stream.readinto(view[got:])
        if not k:
            raise EOFError("stdin closed in the middle of a request")
        got += k


def main():
    if len(sys.argv) != 2:
        reply({"ready": False, "error": "usage: mitsuba_render.py SCENE_DIR"})
        return 2
    global mi, dr, np
    try:
        import drjit as dr
        import mitsuba as mi
        import numpy as np

        mi.set_variant(VARIANT)
        renderer = Renderer(sys.argv[1])
        reply({"ready": True, "mitsuba": mi.__version__, "variant": VARIANT})
    except Exception as e:  # report why, then stop
        traceback.print_exc()
        reply({"ready": False, "error": f"{type(e).__name__}: {e}"})
        return 1
    stdin = sys.stdin.buffer
    while True:
        line = stdin.readline()
        if not line:
            return 0
        # A header that cannot be read leaves the stream out of step: stop.
        try:
            req = json.loads(line)
            n = int(req["n"])
            if n < 0 or n > 1 << 26:
                raise ValueError(f"ray count {n} out of range")
        except Exception as e:
            reply({"ok": False, "error": f"bad request header: {e}"})
            return 1
        try:
            rays = aligned_f32(6 * n)
            read_exact(stdin, rays)
            rays = rays.reshape(n, 6)
            if req["op"] == "echoes":
                out = renderer.echoes(req, rays)
            elif req["op"] == "radiance":
                out = renderer.radiance(req, rays)
            else:
                raise ValueError(f"unknown op {req['op']!r}")
        except EOFError:
            return 0
        except Exception as e:
            traceback.print_exc()
            reply({"ok": False, "error": f"{type(e).__name__}: {e}"})
            continue
        reply({"ok": True, "floats": int(out.size)}, out.astype("<f4").tobytes())


if __name__ == "__main__":
    sys.exit(main())
