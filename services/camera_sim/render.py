"""MuJoCo model of a :class:`SceneSpec` plus its cameras, rendered headless (EGL, Mesa on CPU)."""

from __future__ import annotations

import math
import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported: headless rendering

import mujoco
import numpy as np
import numpy.typing as npt

from common.camera import StereoCalibration
from services.camera_sim.rig import mujoco_camera_axes
from services.camera_sim.scene import SceneSpec

TEXTURE_PX = 512
TEXTURE_SPAN_M = 4.0
OBJECT_TEXTURE_SPAN_M = 4.0


def procedural_texture(seed: int, size: int = TEXTURE_PX) -> npt.NDArray[np.uint8]:
    """Multi-octave value noise: texture at every scale stereo matching needs, no repetition
    within the disparity search range (a checkerboard would be ambiguous)."""
    rng = np.random.default_rng(seed)
    image = np.zeros((size, size), dtype=np.float64)
    for cell_px, weight in ((1, 0.35), (2, 0.3), (4, 0.2), (16, 0.1), (64, 0.05)):
        coarse = rng.random((size // cell_px, size // cell_px))
        image += weight * np.kron(coarse, np.ones((cell_px, cell_px)))
    image = (image - image.min()) / (image.max() - image.min())
    gray = (40 + 200 * image).astype(np.uint8)
    return np.repeat(gray[:, :, None], 3, axis=2)


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


def _shelf_geoms(
    name: str, cx: float, cy: float, yaw: float, size: tuple[float, float, float], rgba: str
) -> list[str]:
    """Legs, two shelves and a top board, all within the shelf's bounding box."""
    sx, sy, sz = size
    c, s = math.cos(yaw), math.sin(yaw)
    leg, board = 0.04, 0.03
    geoms = []
    for k, (lx, ly) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
        ox, oy = lx * (sx / 2 - leg), ly * (sy / 2 - leg)
        geoms.append(
            _box_geom(
                f"{name}_leg{k}",
                (cx + c * ox - s * oy, cy + s * ox + c * oy, sz / 2),
                (leg, leg, sz / 2),
                yaw,
                rgba,
                "object",
            )
        )
    for k, z in enumerate((0.35 * sz, 0.7 * sz, sz - board)):
        geoms.append(
            _box_geom(f"{name}_board{k}", (cx, cy, z), (sx / 2, sy / 2, board), yaw, rgba, "object")
        )
    return geoms


def scene_mjcf(
    scene: SceneSpec, calibrations: list[StereoCalibration], shadows: bool = False
) -> str:
    fx, fy = scene.floor_size_m
    width = max(c.left.width for c in calibrations) if calibrations else 640
    height = max(c.left.height for c in calibrations) if calibrations else 480
    floor_material = "floor" if scene.floor == "textured" else "floor_plain"
    bodies: list[str] = []
    for obj in scene.objects:
        rgba = _rgba(obj.rgba)
        sx, sy, sz = obj.size_m
        x, y = obj.center_xy_m
        if obj.shape == "shelf":
            bodies += _shelf_geoms(obj.name, x, y, obj.yaw_rad, obj.size_m, rgba)
        elif obj.shape == "box":
            bodies.append(
                _box_geom(
                    obj.name, (x, y, sz / 2), (sx / 2, sy / 2, sz / 2), obj.yaw_rad, rgba, "object"
                )
            )
        else:
            bodies.append(
                f'<geom name="{obj.name}" type="cylinder" pos="{x:.4f} {y:.4f} {sz / 2:.4f}" '
                f'size="{sx / 2:.4f} {sz / 2:.4f}" rgba="{rgba}" material="object"/>'
            )
    for wall in scene.walls():
        half = tuple(v / 2 for v in wall.size_m)
        bodies.append(
            _box_geom(
                wall.name,
                wall.center_m,
                (half[0], half[1], half[2]),
                0.0,
                "0.7 0.7 0.65 1",
                "object",
            )
        )
    for m in scene.movers:
        sx, sy, sz = m.size_m
        geom = (
            f'<geom type="box" size="{sx / 2:.4f} {sy / 2:.4f} {sz / 2:.4f}"'
            if m.shape == "box"
            else f'<geom type="cylinder" size="{sx / 2:.4f} {sz / 2:.4f}"'
        )
        bodies.append(
            f'<body name="{m.name}" mocap="true" pos="{m.path_xy_m[0][0]} {m.path_xy_m[0][1]} {sz / 2:.4f}">'
            f'{geom} rgba="{_rgba(m.rgba)}" material="object"/></body>'
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
    return f"""<mujoco model="overgrid_warehouse">
  <visual>
    <global offwidth="{width}" offheight="{height}"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.35 0.35 0.35" specular="0 0 0"/>
    <quality shadowsize="{2048 if shadows else 0}"/>
    <map znear="0.05" zfar="60"/>
  </visual>
  <asset>
    <texture name="noise" type="2d" builtin="flat" width="{TEXTURE_PX}" height="{TEXTURE_PX}" rgb1="0.5 0.5 0.5"/>
    <material name="floor" texture="noise" texuniform="true" texrepeat="{1 / TEXTURE_SPAN_M} {1 / TEXTURE_SPAN_M}" reflectance="0" specular="0"/>
    <material name="floor_plain" rgba="0.55 0.55 0.55 1" reflectance="0" specular="0"/>
    <material name="object" texture="noise" texuniform="true" texrepeat="{1 / OBJECT_TEXTURE_SPAN_M} {1 / OBJECT_TEXTURE_SPAN_M}" reflectance="0" specular="0"/>
  </asset>
  <worldbody>
    <light name="sun0" directional="true" pos="{fx / 3} {fy / 2} 8" dir="0.2 0.1 -1" diffuse="0.45 0.45 0.45" castshadow="{cast}"/>
    <light name="sun1" directional="true" pos="{2 * fx / 3} {fy / 2} 8" dir="-0.2 -0.1 -1" diffuse="0.25 0.25 0.25" castshadow="false"/>
    <geom name="floor" type="plane" pos="{fx / 2} {fy / 2} 0" size="{fx / 2 + 1} {fy / 2 + 1} 0.1" material="{floor_material}"/>
    {chr(10).join("    " + b for b in bodies)}
    {chr(10).join("    " + c for c in cameras)}
  </worldbody>
</mujoco>"""


class SceneRenderer:
    """Renders any of the scene's cameras at any time; one GL context for the whole process."""

    def __init__(
        self,
        scene: SceneSpec,
        calibrations: list[StereoCalibration],
        shadows: bool = False,
        vary_lighting: bool = False,
    ) -> None:
        self.scene = scene
        self.vary_lighting = vary_lighting
        self.model = mujoco.MjModel.from_xml_string(scene_mjcf(scene, calibrations, shadows))
        texture = procedural_texture(scene.texture_seed)
        start = int(self.model.tex_adr[0])
        self.model.tex_data[start : start + texture.size] = texture.reshape(-1)
        self.data = mujoco.MjData(self.model)
        self._base_diffuse = self.model.light_diffuse.copy()
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
        if self.vary_lighting:
            # Slow 40 s cycle between 60 % and 100 % of the base light, as daylight through windows.
            gain = 0.8 + 0.2 * math.sin(2 * math.pi * t_s / 40.0)
            self.model.light_diffuse[:] = self._base_diffuse * gain
        mujoco.mj_forward(self.model, self.data)

    def render_gray(self, camera: str, width: int, height: int) -> npt.NDArray[np.uint8]:
        renderer = self._renderer(width, height)
        renderer.update_scene(self.data, camera=camera)
        rgb = renderer.render()
        # ITU-R BT.601 luma in integers: no OpenCV needed in the sim-only install.
        weights = np.array([77, 150, 29], dtype=np.uint16)
        return ((rgb.astype(np.uint16) @ weights) >> 8).astype(np.uint8)

    def render_rgb(self, camera: str, width: int, height: int) -> npt.NDArray[np.uint8]:
        renderer = self._renderer(width, height)
        renderer.update_scene(self.data, camera=camera)
        return np.asarray(renderer.render())

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
