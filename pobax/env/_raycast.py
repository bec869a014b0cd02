"""A pure-JAX ray caster for MuJoCo (MJX) scenes: small RGB frames that jit and vmap on CPU and GPU.

It renders what the pixel MuJoCo environments (`_pixels.py`) show the agent: one primary ray per pixel (or
`supersample**2` rays, averaged) from a pinhole camera, intersected analytically with every geom of the model
at its current pose (`geom_xpos`, `geom_xmat` of the MJX data), then shaded.

Geometry. Supported geom types: plane, sphere, capsule (the types the Brax robots use), box and ellipsoid.
Other types (cylinder, mesh, height field) are refused when the scene is built. Spheres and capsules are
intersected in world coordinates (a capsule as a segment with a radius), boxes and ellipsoids in the geom's
frame, planes as infinite planes through `geom_xpos` with normal `geom_xmat[:, 2]`. Unlike `mujoco.mjx.ray`,
which stops a plane at its rendered rectangle (`geom_size[:2]`), the floor here is infinite, as it is for
collisions, so that a robot that runs far is still seen on a floor; elsewhere the distances and geom ids
agree with `mjx.ray` (tested). Geoms with zero alpha are skipped, as `mjx.ray` does.

Camera. All primary rays share one origin (a pinhole), so per-geom terms are computed once per frame and the
per-ray work is a few dot products per geom. The camera has a fixed orientation (`azimuth`, `elevation`, in
degrees, MuJoCo's free-camera convention) and a fixed vertical field of view; it looks at a target point that
follows the torso in the horizontal axes marked in `track` (the other coordinates are fixed), from `distance`
metres away. The ray directions are constants computed with NumPy when the scene is built.

Shading. Lambert with one directional light plus ambient: `colour * (ambient + diffuse * max(0, n . l))`,
`n` the analytic surface normal of the geom that was hit. Robot geoms keep their model colour
(`geom_rgba[:, :3]`); planes are drawn as a two-tone checkerboard (`checker_size` metres a square) whose
contrast fades with distance (to limit aliasing near the horizon), so that motion over the floor is visible.
With `shadows=True`, floor points whose ray to the light is blocked by a non-plane geom lose the diffuse
term (one extra ray per pixel). Rays that hit nothing get a vertical sky gradient. Output is uint8
`(height, width, 3)` in [0, 255].

Everything per frame is `jax.numpy` on fixed shapes: `render` jits, vmaps over environments and runs inside
`lax.scan`. It is written to be clean under `jax_numpy_rank_promotion="raise"`.
"""

import dataclasses
import math
from typing import Any

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, UInt8

# MuJoCo geom type codes (`mujoco.mjtGeom`), fixed by MuJoCo's file format.
PLANE, HFIELD, SPHERE, CAPSULE, ELLIPSOID, CYLINDER, BOX, MESH = range(8)
SUPPORTED_TYPES = {PLANE: "plane", SPHERE: "sphere", CAPSULE: "capsule", ELLIPSOID: "ellipsoid", BOX: "box"}
_INF = jnp.inf
_EPS = 1e-9


@dataclasses.dataclass(frozen=True)
class Camera:
    """A tracking pinhole camera with a fixed orientation.

    The camera looks at `target = where(track, torso_pos, 0) + offset` from `distance` metres along the
    direction given by `azimuth` (degrees, about +z from +x) and `elevation` (degrees, negative looks down).
    `fovy` is the vertical field of view in degrees. For example `azimuth=90, elevation=0` is a side view
    looking along +y, with +x to the right of the image.
    """

    distance: float
    azimuth: float
    elevation: float
    fovy: float = 45.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    track: tuple[bool, bool, bool] = (True, True, False)

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Forward, right and up unit vectors of the camera (world frame)."""
        az, el = math.radians(self.azimuth), math.radians(self.elevation)
        forward = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right = right / np.linalg.norm(right)
        up = np.cross(right, forward)
        return forward, right, up

    def ray_directions(self, height: int, width: int) -> np.ndarray:
        """Unit ray directions through the centres of the pixels, shape `(height * width, 3)`, row-major with
        row 0 at the top of the image."""
        forward, right, up = self.basis()
        t = math.tan(math.radians(self.fovy) / 2)
        ys = (1.0 - 2.0 * (np.arange(height) + 0.5) / height) * t
        xs = (2.0 * (np.arange(width) + 0.5) / width - 1.0) * t * width / height
        d = forward[None, None] + xs[None, :, None] * right[None, None] + ys[:, None, None] * up[None, None]
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        return d.reshape(-1, 3).astype(np.float32)

    def origin(self, torso_pos: Float[Array, "3"]) -> Float[Array, "3"]:
        """The camera position for a torso position."""
        forward, _, _ = self.basis()
        target = jnp.where(jnp.asarray(self.track), torso_pos, 0.0) + jnp.asarray(self.offset, jnp.float32)
        return target - self.distance * jnp.asarray(forward, jnp.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """Everything about a model and a camera that does not change between frames (NumPy constants).

    Built once per (model, camera, size) with `Scene.from_model`; compared by identity (so it can be a static
    field of an environment, like the Brax environment itself).
    """

    geom_type: np.ndarray  # (G,) int
    geom_size: np.ndarray  # (G, 3)
    geom_rgb: np.ndarray  # (G, 3) in [0, 1]
    visible: np.ndarray  # (G,) bool: geoms that can be hit
    camera: Camera
    height: int
    width: int
    supersample: int
    shadows: bool
    light_dir: np.ndarray  # (3,) unit vector pointing towards the light
    ambient: float = 0.4
    diffuse: float = 0.6
    checker_size: float = 0.5
    floor_rgb: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.62, 0.66, 0.72), (0.36, 0.40, 0.47))
    checker_fade: float = 6.0  # metres: the checker contrast decays as exp(-distance / checker_fade)
    sky_rgb: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.80, 0.87, 0.95), (0.45, 0.62, 0.85))

    @classmethod
    def from_model(
        cls,
        model,
        camera: Camera,
        height: int = 32,
        width: int = 32,
        *,
        supersample: int = 1,
        shadows: bool = False,
        light_dir: tuple[float, float, float] = (-0.3, -0.6, 1.0),
        **shading,
    ) -> "Scene":
        """A scene for a MuJoCo or MJX model (anything with `geom_type`, `geom_size`, `geom_rgba`)."""
        types = np.asarray(model.geom_type).astype(np.int32)
        bad = sorted({int(t) for t in types} - set(SUPPORTED_TYPES))
        if bad:
            raise NotImplementedError(
                f"The ray caster supports geom types {sorted(SUPPORTED_TYPES.values())}; the model has "
                f"unsupported type codes {bad} (mujoco.mjtGeom)."
            )
        rgba = np.asarray(model.geom_rgba, np.float32)
        light = np.asarray(light_dir, np.float32)
        return cls(
            geom_type=types,
            geom_size=np.asarray(model.geom_size, np.float32),
            geom_rgb=rgba[:, :3],
            visible=rgba[:, 3] > 0,
            camera=camera,
            height=height,
            width=width,
            supersample=supersample,
            shadows=shadows,
            light_dir=light / np.linalg.norm(light),
            **shading,
        )

    def ids(self, *types: int) -> np.ndarray:
        """Indices of the visible geoms of the given types."""
        return np.nonzero(np.isin(self.geom_type, types) & self.visible)[0]

    @property
    def ray_directions(self) -> np.ndarray:
        s = self.supersample
        return self.camera.ray_directions(self.height * s, self.width * s)


# --- Intersection ---------------------------------------------------------------------------------------------
#
# Vectors are tuples of three arrays (x, y, z components) rather than arrays with a trailing axis of 3: every
# operation is then elementwise on (rays, geoms) arrays, which XLA fuses into one loop (reductions over a
# trailing axis of 3 are several times slower on CPU). Ray quantities have shape (R, 1) (or (1, 1) for the
# shared pinhole origin), geom quantities (1, G).

Vec = tuple  # (x, y, z): arrays (or Python floats for constants)


def _vec(x: Array) -> Vec:
    return x[..., 0], x[..., 1], x[..., 2]


def _dot(a: Vec, b: Vec) -> Array:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _sub(a: Vec, b: Vec) -> Vec:
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


def _scale(a: Vec, s: Any) -> Vec:
    return a[0] * s, a[1] * s, a[2] * s


def _col(mat: Array, j: int) -> Vec:
    """Column `j` of rotation matrices `mat` (..., 3, 3): the geom frame's axis `j` in world coordinates."""
    return mat[..., 0, j], mat[..., 1, j], mat[..., 2, j]


def _to_local(v: Vec, mat: Array) -> Vec:
    """`mat^T v` (world to geom frame), with `mat` (..., 3, 3) broadcast against `v`."""
    return tuple(_dot(_col(mat, i), v) for i in range(3))  # type: ignore[return-value]


def _nearest_root(b: Array, c: Array) -> Array:
    """The smallest non-negative root of `t^2 + 2 b t + c = 0`, or inf."""
    h = b * b - c
    s = jnp.sqrt(jnp.maximum(h, 0.0))
    t0, t1 = -b - s, -b + s
    t = jnp.where(t0 >= 0, t0, jnp.where(t1 >= 0, t1, _INF))
    return jnp.where(h >= 0, t, _INF)


def _planes(o: Vec, d: Vec, pos: Vec, mat: Array) -> Array:
    """Infinite planes through `pos` with normal `mat[:, 2]`, front face only (as MuJoCo)."""
    n = _col(mat, 2)
    dn = _dot(d, n)
    t = _dot(_sub(pos, o), n) / jnp.where(dn < -_EPS, dn, -1.0)
    return jnp.where((dn < -_EPS) & (t >= 0), t, _INF)


def _spheres(o: Vec, d: Vec, pos: Vec, size: Array) -> Array:
    oc = _sub(o, pos)
    return _nearest_root(_dot(d, oc), _dot(oc, oc) - jnp.square(size[..., 0]))


def _capsules(o: Vec, d: Vec, pos: Vec, mat: Array, size: Array) -> Array:
    """Capsules as segments `pos -+ half_length * z_axis` swollen by `radius` (Inigo Quilez's formulation)."""
    r, h = size[..., 0], size[..., 1]
    ba = _scale(_col(mat, 2), 2.0 * h)  # segment vector, from its start a = pos - h z
    oa = _sub(o, _sub(pos, _scale(ba, 0.5)))
    baba = jnp.square(2.0 * h)
    bard, baoa, rdoa, oaoa = _dot(d, ba), _dot(oa, ba), _dot(d, oa), _dot(oa, oa)
    qa = baba - bard * bard
    qb = baba * rdoa - baoa * bard
    qc = baba * oaoa - baoa * baoa - r * r * baba
    disc = qb * qb - qa * qc
    t_side = (-qb - jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.where(qa > _EPS, qa, 1.0)
    y = baoa + t_side * bard
    side = (disc >= 0) & (qa > _EPS) & (y > 0) & (y < baba) & (t_side >= 0)
    # Otherwise the nearest hit is on the end cap on the side where the ray meets the cylinder.
    start = y <= 0
    oc = tuple(jnp.where(start, oa[i], oa[i] - ba[i]) for i in range(3))
    t_cap = _nearest_root(_dot(d, oc), _dot(oc, oc) - r * r)
    return jnp.where(side, t_side, t_cap)


def _boxes(o: Vec, d: Vec, pos: Vec, mat: Array, size: Array) -> Array:
    lo, ld = _to_local(_sub(o, pos), mat), _to_local(d, mat)
    near, far = None, None
    for i in range(3):
        inv = 1.0 / jnp.where(jnp.abs(ld[i]) > _EPS, ld[i], _EPS)
        t1, t2 = (-size[..., i] - lo[i]) * inv, (size[..., i] - lo[i]) * inv
        lo_t, hi_t = jnp.minimum(t1, t2), jnp.maximum(t1, t2)
        near = lo_t if near is None else jnp.maximum(near, lo_t)
        far = hi_t if far is None else jnp.minimum(far, hi_t)
    t = jnp.where(near >= 0, near, far)
    return jnp.where((near <= far) & (far >= 0), t, _INF)


def _ellipsoids(o: Vec, d: Vec, pos: Vec, mat: Array, size: Array) -> Array:
    lo, ld = _to_local(_sub(o, pos), mat), _to_local(d, mat)
    inv2 = tuple(1.0 / jnp.square(size[..., i]) for i in range(3))
    sd = (ld[0] * inv2[0], ld[1] * inv2[1], ld[2] * inv2[2])  # diag(1 / size^2) d
    so = (lo[0] * inv2[0], lo[1] * inv2[1], lo[2] * inv2[2])
    a = _dot(sd, ld)
    return _nearest_root(_dot(sd, lo) / a, (_dot(so, lo) - 1.0) / a)


def intersect(
    scene: Scene,
    origins: Float[Array, "o 3"],
    dirs: Float[Array, "r 3"],
    geom_xpos: Float[Array, "G 3"],
    geom_xmat: Float[Array, "G 3 3"],
    types: tuple[int, ...] = tuple(SUPPORTED_TYPES),
) -> tuple[Float[Array, " r"], Array]:
    """The distance along each unit ray to the nearest geom of `types` and that geom's id (inf and -1 on a miss).

    `origins` is one shared origin `(1, 3)` (a pinhole) or one per ray `(R, 3)`.
    """
    o, d = _vec(origins[:, None, :]), _vec(dirs[:, None, :])  # (R|1, 1), (R, 1)
    num_rays = dirs.shape[0]
    dists, ids = [], []
    for kind in types:
        idx = scene.ids(kind)
        if idx.size == 0:
            continue
        pos, mat = _vec(geom_xpos[idx][None]), geom_xmat[idx][None]  # (1, G), (1, G, 3, 3)
        size = jnp.asarray(scene.geom_size[idx])[None]  # (1, G, 3)
        if kind == PLANE:
            t = _planes(o, d, pos, mat)
        elif kind == SPHERE:
            t = _spheres(o, d, pos, size)
        elif kind == CAPSULE:
            t = _capsules(o, d, pos, mat, size)
        elif kind == BOX:
            t = _boxes(o, d, pos, mat, size)
        else:
            t = _ellipsoids(o, d, pos, mat, size)
        dists.append(jnp.broadcast_to(t, (num_rays, idx.size)))
        ids.append(idx)
    if not dists:
        return jnp.full((num_rays,), _INF), jnp.full((num_rays,), -1, jnp.int32)
    dist = jnp.concatenate(dists, axis=1)
    all_ids = jnp.asarray(np.concatenate(ids), jnp.int32)
    t = jnp.min(dist, axis=1)
    k = jnp.argmin(dist, axis=1)
    return t, jnp.where(jnp.isfinite(t), all_ids[k], -1)


# --- Shading -------------------------------------------------------------------------------------------------


def _normals(scene: Scene, points: Vec, geom: Array, geom_xpos: Array, geom_xmat: Array) -> Vec:
    """World-frame unit normals at hit `points` (R,) on geoms `geom` (R,) (any value where nothing is hit)."""
    g = jnp.maximum(geom, 0)
    mat = geom_xmat[g]  # (R, 3, 3)
    q = _to_local(_sub(points, _vec(geom_xpos[g])), mat)  # local hit point
    size = jnp.asarray(scene.geom_size)[g]
    kind = jnp.asarray(scene.geom_type)[g]
    half = size[:, 1]
    # Box: the face whose normalised coordinate is largest.
    ratio = [jnp.abs(q[i]) / jnp.maximum(size[:, i], _EPS) for i in range(3)]
    box_axis = jnp.where((ratio[0] >= ratio[1]) & (ratio[0] >= ratio[2]), 0, jnp.where(ratio[1] >= ratio[2], 1, 2))
    n = []
    for i in range(3):
        sphere = q[i]
        capsule = q[i] - jnp.clip(q[i], -half, half) if i == 2 else q[i]
        box = jnp.where(box_axis == i, jnp.sign(q[i]), 0.0)
        ellipsoid = q[i] / jnp.square(jnp.maximum(size[:, i], _EPS))
        plane = jnp.full_like(q[i], 1.0 if i == 2 else 0.0)
        ni = jnp.where(kind == PLANE, plane, sphere)
        ni = jnp.where(kind == CAPSULE, capsule, ni)
        ni = jnp.where(kind == BOX, box, ni)
        n.append(jnp.where(kind == ELLIPSOID, ellipsoid, ni))
    # Back to world coordinates: n_world = mat @ n_local.
    world = tuple(mat[:, i, 0] * n[0] + mat[:, i, 1] * n[1] + mat[:, i, 2] * n[2] for i in range(3))
    norm = jnp.sqrt(jnp.maximum(_dot(world, world), _EPS))
    return _scale(world, 1.0 / norm)


def render_depth(
    scene: Scene, geom_xpos: Float[Array, "G 3"], geom_xmat: Float[Array, "G 3 3"], torso_pos: Float[Array, "3"]
) -> tuple[Float[Array, "H W"], Array]:
    """Distance to the first hit and the geom id per pixel (no supersampling), for tests and debugging."""
    dirs = jnp.asarray(scene.camera.ray_directions(scene.height, scene.width))
    t, g = intersect(scene, scene.camera.origin(torso_pos)[None], dirs, geom_xpos, geom_xmat)
    return t.reshape(scene.height, scene.width), g.reshape(scene.height, scene.width)


def render(
    scene: Scene, geom_xpos: Float[Array, "G 3"], geom_xmat: Float[Array, "G 3 3"], torso_pos: Float[Array, "3"]
) -> UInt8[Array, "H W 3"]:
    """Render one RGB frame of the geoms at poses (`geom_xpos`, `geom_xmat`), camera tracking `torso_pos`."""
    geom_xpos = geom_xpos.astype(jnp.float32)
    geom_xmat = geom_xmat.astype(jnp.float32)
    dirs_np = scene.ray_directions  # (R, 3) NumPy constants
    dirs = jnp.asarray(dirs_np)
    origin = scene.camera.origin(torso_pos.astype(jnp.float32))
    t, geom = intersect(scene, origin[None], dirs, geom_xpos, geom_xmat)
    hit = geom >= 0
    d = _vec(dirs)
    th = jnp.where(hit, t, 0.0)
    points = tuple(origin[i] + th * d[i] for i in range(3))
    normals = _normals(scene, points, geom, geom_xpos, geom_xmat)
    # Two-sided surfaces: a normal facing away from the camera is flipped.
    normals = _scale(normals, jnp.where(_dot(normals, d) > 0, -1.0, 1.0))

    kind = jnp.asarray(scene.geom_type)[jnp.maximum(geom, 0)]
    on_plane = hit & (kind == PLANE)
    cells = jnp.floor(points[0] / scene.checker_size) + jnp.floor(points[1] / scene.checker_size)
    odd = cells - 2.0 * jnp.floor(0.5 * cells)  # 0 or 1
    fade = jnp.exp(-th / scene.checker_fade)
    light_dir = tuple(float(x) for x in scene.light_dir)
    lambert = jnp.maximum(_dot(normals, light_dir), 0.0)  # type: ignore[arg-type]
    if scene.shadows:
        # A shadow ray from each floor point towards the light, against the non-plane geoms.
        starts = jnp.stack([p + 1e-3 * n for p, n in zip(points, normals)], axis=1)
        solid = tuple(k for k in SUPPORTED_TYPES if k != PLANE)
        light = jnp.broadcast_to(jnp.asarray(scene.light_dir, jnp.float32)[None], dirs.shape)
        ts, _ = intersect(scene, starts, light, geom_xpos, geom_xmat, solid)
        lambert = jnp.where(on_plane & jnp.isfinite(ts), 0.0, lambert)
    shade = scene.ambient + scene.diffuse * lambert
    rgb = jnp.asarray(scene.geom_rgb)[jnp.maximum(geom, 0)]  # (R, 3)
    channels = []
    for c in range(3):
        light_c, dark_c = scene.floor_rgb[0][c], scene.floor_rgb[1][c]
        mean_c = 0.5 * (light_c + dark_c)
        floor = mean_c + fade * ((1.0 - odd) * light_c + odd * dark_c - mean_c)
        surface = jnp.where(on_plane, floor, rgb[:, c]) * shade
        horizon, zenith = scene.sky_rgb[0][c], scene.sky_rgb[1][c]
        sky = horizon + np.clip(dirs_np[:, 2], 0.0, 1.0) * (zenith - horizon)  # constant per pixel
        channels.append(jnp.where(hit, surface, jnp.asarray(sky, jnp.float32)))
    colour = jnp.stack(channels, axis=-1)

    s = scene.supersample
    image = colour.reshape(scene.height, s, scene.width, s, 3).mean(axis=(1, 3))
    return jnp.clip(jnp.round(image * 255.0), 0.0, 255.0).astype(jnp.uint8)
