"""MuJoCo model of a :class:`SceneSpec` plus its cameras, rendered headless (EGL, Mesa on CPU)."""

from __future__ import annotations

import math
import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported: headless rendering

import mujoco
import numpy as np
import numpy.typing as npt

from common.camera import StereoCalibration
from services.camera_sim.lighting import Lighting, switched_share
from services.camera_sim.rig import floor_points_xy_m, mujoco_camera_axes
from services.camera_sim.scene import MarkingSpec, ObjectSpec, SceneSpec

TEXTURE_PX = 512
SWITCHED_LEVEL_GRID_PX = (64, 48)
"""A camera's mean share of the light with the circuit off is taken over this grid of its view."""
CONCRETE_PX = 1024
FLOOR_TEXELS_PER_M = 64.0
"""The floor's texture density (15.6 mm texels): the speckle tile repeats every 8 m, the concrete
tile every 16 m (its control joints 8 m apart)."""
FLOOR_MARGIN_M = 1.0
"""The floor plane reaches this far past the floor on every side (under the walls)."""
SURFACE_PX = 256
SURFACE_SPAN_M = 2.0
"""Cardboard, wood, fabric: 7.8 mm texels, repeating every 2 m."""
PAINT_SUBSAMPLES = 4
"""A marking's coverage of a floor texel is sampled on a 4 × 4 grid: its edges fall between
texels as a real line's edge falls between pixels, so the texture's filtering blurs them as a
lens does."""


def procedural_texture(seed: int, size: int = TEXTURE_PX) -> npt.NDArray[np.uint8]:
    """Multi-octave value noise: texture at every scale stereo matching needs, no repetition
    within the disparity search range (a checkerboard would be ambiguous). The ideal world's
    ``speckle`` floor; no real floor looks like it."""
    rng = np.random.default_rng(seed)
    image = np.zeros((size, size), dtype=np.float64)
    for cell_px, weight in ((1, 0.35), (2, 0.3), (4, 0.2), (16, 0.1), (64, 0.05)):
        coarse = rng.random((size // cell_px, size // cell_px))
        image += weight * np.kron(coarse, np.ones((cell_px, cell_px)))
    image = (image - image.min()) / (image.max() - image.min())
    return _gray_rgb(40 + 200 * image)


def _gray_rgb(values: npt.NDArray[np.float64]) -> npt.NDArray[np.uint8]:
    gray = np.clip(values, 0, 255).astype(np.uint8)
    return np.repeat(gray[:, :, None], 3, axis=2)


def smooth_noise(rng: np.random.Generator, size: int, cell_px: int) -> npt.NDArray[np.float64]:
    """Zero-mean, unit-variance value noise with features of ``cell_px``, bilinearly interpolated
    (no blocky edges a real surface lacks) and periodic, so the texture tiles seamlessly."""
    cells = max(1, size // cell_px)
    coarse = rng.standard_normal((cells, cells))
    position = np.arange(size) * cells / size
    low = np.floor(position).astype(int)
    frac = position - low
    high = (low + 1) % cells
    rows = coarse[low] * (1 - frac)[:, None] + coarse[high] * frac[:, None]
    image: npt.NDArray[np.float64] = (
        rows[:, low] * (1 - frac)[None, :] + rows[:, high] * frac[None, :]
    )
    normalised: npt.NDArray[np.float64] = (image - image.mean()) / max(float(image.std()), 1e-9)
    return normalised


def concrete_texture(seed: int, size: int = CONCRETE_PX) -> npt.NDArray[np.uint8]:
    """Troweled concrete: low-contrast grain and mottling at several scales, a few soft stains,
    and saw-cut control joints. At the cameras' 1–2 cm pixels only a few percent of contrast is
    left: the weak texture a real floor gives stereo. The tile is periodic; at
    :data:`FLOOR_TEXELS_PER_M` its stains are 0.8–3 m across and its joints 8 m apart."""
    rng = np.random.default_rng(seed + 1_000_003)
    image = np.full((size, size), 0.85)
    for cell_px, contrast in ((1, 0.02), (3, 0.02), (12, 0.025), (48, 0.03), (192, 0.04)):
        image += contrast * smooth_noise(rng, size, cell_px)
    y, x = np.mgrid[0:size, 0:size] / size  # in tiles
    for _ in range(6):
        cx, cy = rng.uniform(0, 1, 2)
        rx, ry = rng.uniform(0.025, 0.1, 2)
        dx = (x - cx + 0.5) % 1.0 - 0.5
        dy = (y - cy + 0.5) % 1.0 - 0.5
        image *= 1.0 - rng.uniform(0.06, 0.14) * np.exp(-((dx / rx) ** 2 + (dy / ry) ** 2))
    for start in (0, size // 2):  # saw cuts, one texel wide
        image[start, :] *= 0.75
        image[:, start] *= 0.75
    return _gray_rgb(255 * image)


def surface_texture(seed: int, kind: str, size: int = SURFACE_PX) -> npt.NDArray[np.uint8]:
    """Near-white luminance textures that the material colour tints: ``cardboard`` (fibre
    mottling), ``wood`` (grain along one axis), ``fabric`` (fine weave)."""
    rng = np.random.default_rng([seed, sum(map(ord, kind))])
    image = np.full((size, size), 0.9)
    if kind == "cardboard":
        image += 0.025 * smooth_noise(rng, size, 2) + 0.03 * smooth_noise(rng, size, 16)
    elif kind == "wood":
        grain = smooth_noise(rng, size, 8)[:, :1] + 0.5 * smooth_noise(rng, size, 32)
        image += 0.06 * grain + 0.03 * smooth_noise(rng, size, 2)
    else:
        image += 0.05 * smooth_noise(rng, size, 1) + 0.05 * smooth_noise(rng, size, 6)
    return _gray_rgb(255 * image)


FLOOR_FINISHES = {
    "concrete": ((0.72, 0.72, 0.7), 'specular="0.15" shininess="0.3"'),
    "speckle": ((1.0, 1.0, 1.0), 'specular="0"'),
    "plain": ((0.62, 0.62, 0.62), 'specular="0.1" shininess="0.3"'),
}
"""Each floor kind's material colour and sheen. MuJoCo lights the material's colour and clamps it
at 1 before the texture multiplies it (the site's light lifts white to 1.5): the material holds
the floor's colour, below the clamp, and the texture modulates it; paint brighter than the
material saturates there, as brighter surfaces do everywhere in these renders."""
PLAIN_FLOOR_ALBEDO = 0.55


def floor_texture_shape(floor_size_m: tuple[float, float]) -> tuple[int, int]:
    """Rows × columns of the floor texture: the whole floor plane, margins included, once."""
    fx, fy = floor_size_m
    return (
        math.ceil((fy + 2 * FLOOR_MARGIN_M) * FLOOR_TEXELS_PER_M),
        math.ceil((fx + 2 * FLOOR_MARGIN_M) * FLOOR_TEXELS_PER_M),
    )


def floor_texture(scene: SceneSpec) -> npt.NDArray[np.uint8]:
    """The floor's colour over the whole floor plane: its kind's surface, then the markings
    painted on it (paint is flat: a thin box's side face would show as a raised edge).

    Texel (row, col) covers x from ``col / FLOOR_TEXELS_PER_M − FLOOR_MARGIN_M`` and y down from
    ``floor_y_m + FLOOR_MARGIN_M − row / FLOOR_TEXELS_PER_M``: MuJoCo maps a uniform texture on a
    plane from its −x, +y corner (checked against the calibration by a render test)."""
    rows, cols = floor_texture_shape(scene.floor_size_m)
    material = np.asarray(FLOOR_FINISHES[scene.floor][0], dtype=np.float32)
    if scene.floor == "plain":
        surface = _gray_rgb(np.full((1, 1), 255 * PLAIN_FLOOR_ALBEDO / float(material.max())))
    elif scene.floor == "speckle":
        surface = procedural_texture(scene.texture_seed)
    else:
        surface = concrete_texture(scene.texture_seed)
    tile_rows, tile_cols = surface.shape[:2]
    image = surface[np.arange(rows) % tile_rows][:, np.arange(cols) % tile_cols].astype(np.float32)
    for mark in scene.markings:
        _paint(image, mark, scene.floor_size_m[1], material)
    painted: npt.NDArray[np.uint8] = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    return painted


def _paint(
    image: npt.NDArray[np.float32],
    mark: MarkingSpec,
    floor_y_m: float,
    material: npt.NDArray[np.float32],
) -> None:
    """Blend one marking into the floor texture by its coverage of each texel (its colour over the
    floor's ``material`` colour, saturating where brighter)."""
    (cx, cy), (length, width) = mark.center_xy_m, mark.size_m
    c, s = math.cos(mark.yaw_rad), math.sin(mark.yaw_rad)
    reach_x = abs(c) * length / 2 + abs(s) * width / 2
    reach_y = abs(s) * length / 2 + abs(c) * width / 2
    top_m = floor_y_m + FLOOR_MARGIN_M
    col0 = max(0, math.floor((cx - reach_x + FLOOR_MARGIN_M) * FLOOR_TEXELS_PER_M))
    col1 = min(image.shape[1], math.ceil((cx + reach_x + FLOOR_MARGIN_M) * FLOOR_TEXELS_PER_M))
    row0 = max(0, math.floor((top_m - cy - reach_y) * FLOOR_TEXELS_PER_M))
    row1 = min(image.shape[0], math.ceil((top_m - cy + reach_y) * FLOOR_TEXELS_PER_M))
    if col1 <= col0 or row1 <= row0:
        return
    offsets = (np.arange(PAINT_SUBSAMPLES) + 0.5) / PAINT_SUBSAMPLES
    col_samples = (np.arange(col0, col1)[:, None] + offsets[None, :]).ravel()
    row_samples = (np.arange(row0, row1)[:, None] + offsets[None, :]).ravel()
    dx = col_samples / FLOOR_TEXELS_PER_M - FLOOR_MARGIN_M - cx
    dy = top_m - row_samples / FLOOR_TEXELS_PER_M - cy
    along = c * dx[None, :] + s * dy[:, None]
    across = -s * dx[None, :] + c * dy[:, None]
    inside = (np.abs(along) <= length / 2) & (np.abs(across) <= width / 2)
    coverage = inside.reshape(row1 - row0, PAINT_SUBSAMPLES, col1 - col0, PAINT_SUBSAMPLES).mean(
        axis=(1, 3), dtype=np.float32
    )[:, :, None]
    paint = np.minimum(np.asarray(mark.rgba[:3], dtype=np.float32) / material, 1.0) * 255
    window = image[row0:row1, col0:col1]
    window += coverage * (paint - window)


def _rgba(values: tuple[float, float, float, float]) -> str:
    return " ".join(f"{v:.3f}" for v in values)


def _box_geom(
    name: str,
    pos: tuple[float, float, float],
    half: tuple[float, float, float],
    yaw: float,
    rgba: str,
    material: str,
) -> str:
    quat = f"{math.cos(yaw / 2):.6f} 0 0 {math.sin(yaw / 2):.6f}"
    return (
        f'<geom name="{name}" type="box" pos="{pos[0]:.4f} {pos[1]:.4f} {pos[2]:.4f}" '
        f'size="{half[0]:.4f} {half[1]:.4f} {half[2]:.4f}" quat="{quat}" rgba="{rgba}" '
        f'material="{material}"/>'
    )


def _local_boxes(
    name: str,
    obj: ObjectSpec,
    parts: list[tuple[tuple[float, float, float], tuple[float, float, float], str, str]],
) -> list[str]:
    """Boxes given in the object's own frame (centre offset, half sizes, rgba, material)."""
    c, s = math.cos(obj.yaw_rad), math.sin(obj.yaw_rad)
    cx, cy = obj.center_xy_m
    return [
        _box_geom(
            f"{name}_{k}",
            (cx + c * ox - s * oy, cy + s * ox + c * oy, oz),
            half,
            obj.yaw_rad,
            rgba,
            mat,
        )
        for k, ((ox, oy, oz), half, rgba, mat) in enumerate(parts)
    ]


LEG_M, BOARD_M = 0.04, 0.03
DECK_BOARD_M = 0.022
TAPE_M, LABEL_M = (0.05, 0.002), (0.15, 0.1)


def _shelf_geoms(obj: ObjectSpec, rgba: str, material: str) -> list[str]:
    """Legs, two shelves and a top board, all within the shelf's bounding box."""
    sx, sy, sz = obj.size_m
    parts = [
        (
            (lx * (sx / 2 - LEG_M), ly * (sy / 2 - LEG_M), sz / 2),
            (LEG_M, LEG_M, sz / 2),
            rgba,
            material,
        )
        for lx, ly in ((1, 1), (1, -1), (-1, 1), (-1, -1))
    ]
    board_rgba, board_material = (rgba, material) if obj.plain else ("0.75 0.62 0.45 1", "wood")
    parts += [
        ((0.0, 0.0, z), (sx / 2, sy / 2, BOARD_M), board_rgba, board_material)
        for z in (0.35 * sz, 0.7 * sz, sz - BOARD_M)
    ]
    return _local_boxes(obj.name, obj, parts)


def _pallet_geoms(obj: ObjectSpec, rgba: str, material: str) -> list[str]:
    """Five top deck boards along the length with gaps, on three stringers."""
    sx, sy, sz = obj.size_m
    stringer_h = sz - DECK_BOARD_M
    parts = [
        ((0.0, y, stringer_h / 2), (sx / 2, 0.05, stringer_h / 2), rgba, material)
        for y in (-(sy / 2 - 0.05), 0.0, sy / 2 - 0.05)
    ]
    widths = (0.145, 0.1, 0.145, 0.1, 0.145)
    gap = (sy - sum(widths)) / (len(widths) - 1)
    y = -sy / 2
    for width in widths:
        parts.append(
            (
                (0.0, y + width / 2, sz - DECK_BOARD_M / 2),
                (sx / 2, width / 2, DECK_BOARD_M / 2),
                rgba,
                material,
            )
        )
        y += width + gap
    return _local_boxes(obj.name, obj, parts)


def _carton_geoms(obj: ObjectSpec, rgba: str, material: str, rng: np.random.Generator) -> list[str]:
    """A cardboard box: the carton, packing tape across its top, a shipping label with a barcode."""
    sx, sy, sz = obj.size_m
    parts = [((0.0, 0.0, sz / 2), (sx / 2, sy / 2, sz / 2), rgba, material)]
    if not obj.plain:
        tape_w, thin = TAPE_M
        parts.append(
            ((0.0, 0.0, sz + thin / 2), (sx / 2, tape_w / 2, thin / 2), "0.82 0.7 0.5 1", "tape")
        )
        lx, ly = LABEL_M
        ox = float(rng.uniform(-1, 1)) * max(0.0, sx / 2 - lx / 2 - 0.03)
        oy = (sy / 4 + tape_w / 4) * float(rng.choice([-1.0, 1.0]))
        parts.append(((ox, oy, sz + thin), (lx / 2, ly / 2, thin / 2), "0.95 0.95 0.93 1", "paint"))
        for k, width in enumerate((0.006, 0.003, 0.008, 0.004, 0.006)):
            parts.append(
                (
                    (ox - 0.05 + 0.018 * k, oy, sz + 1.5 * thin),
                    (width / 2, ly / 3, thin / 2),
                    "0.1 0.1 0.1 1",
                    "paint",
                )
            )
    return _local_boxes(obj.name, obj, parts)


def _object_geoms(obj: ObjectSpec, rng: np.random.Generator) -> list[str]:
    rgba = _rgba(obj.rgba)
    if obj.plain:
        material = "paint"
    else:
        material = {"box": "cardboard", "pallet": "wood", "shelf": "paint", "cylinder": "fabric"}[
            obj.shape
        ]
    if obj.shape == "shelf":
        return _shelf_geoms(obj, rgba, material)
    if obj.shape == "pallet":
        return _pallet_geoms(obj, rgba, material)
    if obj.shape == "box":
        return _carton_geoms(obj, rgba, material, rng)
    sx, _sy, sz = obj.size_m
    x, y = obj.center_xy_m
    return [
        f'<geom name="{obj.name}" type="cylinder" pos="{x:.4f} {y:.4f} {sz / 2:.4f}" '
        f'size="{sx / 2:.4f} {sz / 2:.4f}" rgba="{rgba}" material="{material}"/>'
    ]


TEXTURES = {
    "concrete": (CONCRETE_PX, CONCRETE_PX),
    "cardboard": (SURFACE_PX, SURFACE_PX),
    "wood": (SURFACE_PX, SURFACE_PX),
    "fabric": (SURFACE_PX, SURFACE_PX),
}
"""Textures of fixed size (the floor's is sized to the scene)."""


def _texrepeat(span_m: float) -> float:
    """MuJoCo's ``texrepeat`` for a uniform 2-D texture that repeats every ``span_m``: it lays a
    texture over 2 / texrepeat metres (measured on renders)."""
    return 2.0 / span_m


def scene_mjcf(
    scene: SceneSpec, calibrations: list[StereoCalibration], shadows: bool = False
) -> str:
    fx, fy = scene.floor_size_m
    width = max(c.left.width for c in calibrations) if calibrations else 640
    height = max(c.left.height for c in calibrations) if calibrations else 480
    rng = np.random.default_rng(scene.texture_seed)
    bodies: list[str] = []
    for obj in scene.objects:
        bodies += _object_geoms(obj, rng)
    for wall in scene.walls():
        half = tuple(v / 2 for v in wall.size_m)
        bodies.append(
            _box_geom(
                wall.name,
                wall.center_m,
                (half[0], half[1], half[2]),
                0.0,
                "0.8 0.8 0.78 1",
                "concrete",
            )
        )
    for m in scene.movers:
        sx, sy, sz = m.size_m
        geom = (
            f'<geom type="box" size="{sx / 2:.4f} {sy / 2:.4f} {sz / 2:.4f}"'
            if m.shape == "box"
            else f'<geom type="cylinder" size="{sx / 2:.4f} {sz / 2:.4f}"'
        )
        material = "paint" if m.shape == "box" else "fabric"
        bodies.append(
            f'<body name="{m.name}" mocap="true" pos="{m.path_xy_m[0][0]} {m.path_xy_m[0][1]} {sz / 2:.4f}">'
            f'{geom} rgba="{_rgba(m.rgba)}" material="{material}"/></body>'
        )
    cameras = []
    for calib in calibrations:
        for side, cam in (("left", calib.left), ("right", calib.right)):
            xyaxes, fovy = mujoco_camera_axes(cam)
            pos = cam.position_world
            cameras.append(
                f'<camera name="{calib.pair}_{side}" pos="{pos[0]:.5f} {pos[1]:.5f} {pos[2]:.5f}" '
                f'xyaxes="{" ".join(f"{v:.6f}" for v in xyaxes)}" fovy="{fovy:.6f}"/>'
            )
    cast = "true" if shadows else "false"
    floor_rows, floor_cols = floor_texture_shape(scene.floor_size_m)
    textures = "\n    ".join(
        f'<texture name="{name}" type="2d" builtin="flat" width="{w}" height="{h}" rgb1="0.5 0.5 0.5"/>'
        for name, (w, h) in {**TEXTURES, "floor": (floor_cols, floor_rows)}.items()
    )
    floor_repeat = (
        _texrepeat(floor_cols / FLOOR_TEXELS_PER_M),
        _texrepeat(floor_rows / FLOOR_TEXELS_PER_M),
    )
    concrete_repeat = _texrepeat(CONCRETE_PX / FLOOR_TEXELS_PER_M)
    surface_repeat = _texrepeat(SURFACE_SPAN_M)
    return f"""<mujoco model="overgrid_warehouse">
  <visual>
    <global offwidth="{width}" offheight="{height}"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.35 0.35 0.35" specular="0 0 0"/>
    <quality shadowsize="{2048 if shadows else 0}"/>
    <map znear="0.05" zfar="60"/>
  </visual>
  <asset>
    {textures}
    <material name="floor" texture="floor" texuniform="true" texrepeat="{floor_repeat[0]!r} {floor_repeat[1]!r}" rgba="{_rgba((*FLOOR_FINISHES[scene.floor][0], 1.0))}" reflectance="0" {FLOOR_FINISHES[scene.floor][1]}/>
    <material name="concrete" texture="concrete" texuniform="true" texrepeat="{concrete_repeat} {concrete_repeat}" rgba="0.72 0.72 0.7 1" reflectance="0" specular="0.15" shininess="0.3"/>
    <material name="cardboard" texture="cardboard" texuniform="true" texrepeat="{surface_repeat} {surface_repeat}" reflectance="0" specular="0"/>
    <material name="wood" texture="wood" texuniform="true" texrepeat="{surface_repeat} {surface_repeat}" reflectance="0" specular="0"/>
    <material name="fabric" texture="fabric" texuniform="true" texrepeat="{surface_repeat} {surface_repeat}" reflectance="0" specular="0"/>
    <material name="paint" reflectance="0" specular="0.1" shininess="0.3"/>
    <material name="tape" reflectance="0" specular="0.4" shininess="0.6"/>
  </asset>
  <worldbody>
    <light name="sun0" directional="true" pos="{fx / 3} {fy / 2} 8" dir="0.2 0.1 -1" diffuse="0.45 0.45 0.45" castshadow="{cast}"/>
    <light name="sun1" directional="true" pos="{2 * fx / 3} {fy / 2} 8" dir="-0.2 -0.1 -1" diffuse="0.25 0.25 0.25" castshadow="false"/>
    <geom name="floor" type="plane" pos="{fx / 2} {fy / 2} 0" size="{fx / 2 + FLOOR_MARGIN_M} {fy / 2 + FLOOR_MARGIN_M} 0.1" material="floor"/>
    {chr(10).join("    " + b for b in bodies)}
    {chr(10).join("    " + c for c in cameras)}
  </worldbody>
</mujoco>"""


def texture_images(scene: SceneSpec) -> dict[str, npt.NDArray[np.uint8]]:
    seed = scene.texture_seed
    return {
        "floor": floor_texture(scene),
        "concrete": concrete_texture(seed),
        **{kind: surface_texture(seed, kind) for kind in ("cardboard", "wood", "fabric")},
    }


class SceneRenderer:
    """Renders any of the scene's cameras at any time; one GL context for the whole process."""

    def __init__(
        self,
        scene: SceneSpec,
        calibrations: list[StereoCalibration],
        shadows: bool = False,
        lighting: Lighting | None = None,
    ) -> None:
        self.scene = scene
        self.lighting = lighting or Lighting()
        self.model = mujoco.MjModel.from_xml_string(scene_mjcf(scene, calibrations, shadows))
        for name, texture in texture_images(scene).items():
            index = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_TEXTURE, name)
            start = int(self.model.tex_adr[index])
            self.model.tex_data[start : start + texture.size] = texture.reshape(-1)
        self.data = mujoco.MjData(self.model)
        self._cameras = {
            f"{c.pair}_{side}": getattr(c, side) for c in calibrations for side in ("left", "right")
        }
        self._switched_shares: dict[tuple[str, int, int], npt.NDArray[np.float32]] = {}
        self._switched_levels: dict[str, float] = {}
        self._switched_off = False
        self._base_diffuse = self.model.light_diffuse.copy()
        self._base_headlight = (
            self.model.vis.headlight.ambient.copy(),
            self.model.vis.headlight.diffuse.copy(),
        )
        width = max((c.left.width for c in calibrations), default=640)
        height = max((c.left.height for c in calibrations), default=480)
        self._renderers: dict[tuple[int, int], mujoco.Renderer] = {}
        self._default_size = (width, height)

    def _renderer(self, width: int, height: int) -> mujoco.Renderer:
        key = (width, height)
        if key not in self._renderers:
            self._renderers[key] = mujoco.Renderer(self.model, height=height, width=width)
        return self._renderers[key]

    def set_time(self, t_s: float) -> None:
        for index, mover in enumerate(self.scene.movers):
            (x, y), _ = mover.state_at(t_s)
            self.data.mocap_pos[index] = (x, y, mover.size_m[2] / 2)
        level = self.lighting.drift_level(t_s)
        self._switched_off = self.lighting.switched_off(t_s)
        self.model.light_diffuse[:] = self._base_diffuse * level
        self.model.vis.headlight.ambient[:] = self._base_headlight[0] * level
        self.model.vis.headlight.diffuse[:] = self._base_headlight[1] * level
        mujoco.mj_forward(self.model, self.data)

    def render_gray(self, camera: str, width: int, height: int) -> npt.NDArray[np.uint8]:
        # ITU-R BT.601 luma in integers: no OpenCV needed in the sim-only install.
        weights = np.array([77, 150, 29], dtype=np.uint16)
        rgb = self._render_rgb(camera, width, height)
        gray: npt.NDArray[np.uint8] = ((rgb.astype(np.uint16) @ weights) >> 8).astype(np.uint8)
        if self._switched_off:
            gray = np.asarray(gray * self._switched_share(camera, width, height) + 0.5, np.uint8)
        return gray

    def render_radiance(self, camera: str, width: int, height: int) -> npt.NDArray[np.float32]:
        """Relative scene radiance (luma, 1.0 = white under nominal light): what a camera's
        :class:`~services.camera_sim.sensor.CameraSensor` turns into a frame."""
        rgb = self._render_rgb(camera, width, height).astype(np.float32)
        radiance: npt.NDArray[np.float32] = rgb @ np.array(
            [0.299 / 255, 0.587 / 255, 0.114 / 255], dtype=np.float32
        )
        if self._switched_off:
            radiance *= self._switched_share(camera, width, height)
        return radiance

    def render_rgb(self, camera: str, width: int, height: int) -> npt.NDArray[np.uint8]:
        rgb = self._render_rgb(camera, width, height)
        if not self._switched_off:
            return rgb
        share = self._switched_share(camera, width, height)[..., None]
        return np.asarray(rgb * share + 0.5, np.uint8)

    def _render_rgb(self, camera: str, width: int, height: int) -> npt.NDArray[np.uint8]:
        """MuJoCo's render: every luminaire on (at the drift's level)."""
        renderer = self._renderer(width, height)
        renderer.update_scene(self.data, camera=camera)
        return np.asarray(renderer.render())

    def switched_level(self, camera: str) -> float:
        """The share of its view's light a camera keeps while the circuit is off (the mean of
        :func:`switched_share` over its view, on a 64 × 48 grid: the share varies over metres):
        the size of its auto-exposure's step. Asked at every capture, lights switching or not."""
        if camera not in self._switched_levels:
            share = self._switched_share(camera, *SWITCHED_LEVEL_GRID_PX)
            self._switched_levels[camera] = float(share.mean())
        return self._switched_levels[camera]

    def _switched_share(self, camera: str, width: int, height: int) -> npt.NDArray[np.float32]:
        """:func:`switched_share` where each pixel's ray meets the floor, once per camera: the
        light's ratio varies over metres, so an object a metre up takes its floor's (a point seen
        by both cameras of a pair takes nearly the same: their rays meet the floor 0.1 m apart)."""
        key = (camera, width, height)
        if key not in self._switched_shares:
            floor_xy_m = floor_points_xy_m(self._cameras[camera], width, height)
            share = switched_share(floor_xy_m, self.scene.floor_size_m)
            self._switched_shares[key] = share.astype(np.float32)
        return self._switched_shares[key]

    def render_depth(self, camera: str, width: int, height: int) -> npt.NDArray[np.float32]:
        """Depth along the optical axis (OpenCV's z), metres."""
        renderer = self._renderer(width, height)
        renderer.enable_depth_rendering()
        try:
            renderer.update_scene(self.data, camera=camera)
            return np.asarray(renderer.render(), dtype=np.float32)
        finally:
            renderer.disable_depth_rendering()

    def close(self) -> None:
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()
