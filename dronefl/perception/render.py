"""Offscreen MuJoCo rendering of a drone's downward camera frame (SPEC §2, §3).

The scene is built once from a :class:`~dronefl.sim.environment.FarmEnvironment` (static
geometry) and then only the mocap bodies move per frame: one vehicle box per target id, painted
in :mod:`dronefl.perception.palette`, and the camera. Geometry matches the simulator exactly:

* ground ``z = 0`` with a speckled soil (``crop_field``, ``open``) or grass (``orchard``) texture;
* ``crop_field``: a crop row (a low green box ``CROP_WIDTH`` m wide, ``CROP_HEIGHT`` m tall) on
  every lane boundary between the headlands;
* ``orchard``: a tree at every :attr:`FarmEnvironment.trees` position, trunk plus a vertical
  cylinder canopy of ``canopy_radius`` between ``canopy_bottom`` and ``canopy_top`` m, the very
  volume :meth:`FarmEnvironment.visible` tests, so rendered occlusion equals simulated occlusion;
* each vehicle a ``length x width x height`` m box on the ground, turned to its heading.

The camera is the :class:`~dronefl.sim.camera.PinholeCamera`: it looks straight down, image-right
is ``(cos yaw, sin yaw)``. MuJoCo only knows a vertical field of view and square pixels, so the
frame is drawn directly at the detector size ``detector_px`` x ``detector_px`` with the OpenGL
frustum's half-width set from the horizontal FOV: this is the 1280 x 720 sensor image already
resized to the square detector image, in one pass (2.25x fewer pixels than rendering 1280 x
720 and resizing). Shadows and reflections are off (they cost ~4x and add nothing here).

Headless: ``MUJOCO_GL`` defaults to ``egl`` (Mesa llvmpipe on a CPU); ``osmesa`` also works.
It is read when MuJoCo is first imported, so import this module before anything imports mujoco.
Orchard trees outside the view are hidden per frame (MuJoCo skips geoms with alpha 0).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from dronefl.config import Scenario, VehicleSpec
from dronefl.perception.palette import MAX_TARGETS, target_colour
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.environment import FarmEnvironment
from dronefl.types import CameraView, TargetState

os.environ.setdefault("MUJOCO_GL", "egl")
import mujoco  # noqa: E402  (MUJOCO_GL must be set before the import)

#: Crop rows: width and height, m.
CROP_WIDTH = 1.6
CROP_HEIGHT = 0.4
#: Tree trunk radius, m.
TRUNK_RADIUS = 0.15
#: Ground plane margin around the field, m (a 70 m high camera sees ~60 m past its position).
GROUND_MARGIN = 150.0
#: Where vehicles absent from a frame are parked (below the ground, never visible), m.
_PARKED_Z = -50.0

_SOIL = ("0.42 0.31 0.20", "0.30 0.22 0.14")
_GRASS = ("0.30 0.42 0.18", "0.22 0.32 0.12")


class SceneRenderer:
    """Renders detector-size RGB frames of one environment.

    ``target_ids`` are the vehicles the scene holds (each gets its palette colour); a frame may
    show any subset of them. Frames are ``(detector_px, detector_px, 3)`` uint8, row 0 at the top
    of the image (image y down), the layout of :class:`~dronefl.types.CameraView.image`.
    """

    def __init__(
        self,
        camera: PinholeCamera,
        vehicle: VehicleSpec,
        environment: FarmEnvironment,
        target_ids: Sequence[int] = tuple(range(1, MAX_TARGETS + 1)),
    ) -> None:
        self.camera = camera
        self.vehicle = vehicle
        self.environment = environment
        self.target_ids = tuple(int(i) for i in target_ids)
        for i in self.target_ids:
            target_colour(i)  # raises for an id without a colour
        self.size_px = camera.detector_px
        self.model = mujoco.MjModel.from_xml_string(self._scene_xml())
        self.data = mujoco.MjData(self.model)
        self._renderer = mujoco.Renderer(
            self.model, self.size_px, self.size_px, max_geom=self.model.ngeom + 16
        )
        self._mocap = {
            i: int(self.model.body_mocapid[self.model.body(f"vehicle{i}").id])
            for i in self.target_ids
        }
        self._camera_mocap = int(self.model.body_mocapid[self.model.body("drone").id])
        self._camera_id = self.model.camera("down").id
        # Tree geoms (trunks and canopies): culled per frame to those the camera can see.
        self._tree_geoms = np.flatnonzero(self.model.geom_type == mujoco.mjtGeom.mjGEOM_CYLINDER)

    @classmethod
    def from_scenario(
        cls, scenario: Scenario, environment: FarmEnvironment | None = None
    ) -> SceneRenderer:
        """A renderer for ``scenario``'s camera, vehicles and (unless given) environment."""
        env = environment or FarmEnvironment(scenario.environment, scenario.field)
        return cls(
            PinholeCamera.from_spec(scenario.camera), scenario.vehicle, env, scenario.target_ids
        )

    def render(
        self, camera_position: np.ndarray, yaw: float, targets: Sequence[TargetState]
    ) -> np.ndarray:
        """Frame seen from ``camera_position`` ``(3,)`` m with camera ``yaw`` rad.

        ``targets`` not in :attr:`target_ids` raise; scene vehicles missing from ``targets`` are
        not drawn. Returns ``(detector_px, detector_px, 3)`` uint8 RGB.
        """
        camera_position = np.asarray(camera_position, dtype=float)
        if camera_position.shape != (3,) or camera_position[2] <= self.vehicle.height:
            raise ValueError(
                f"camera_position must be (x, y, z) above the vehicles, got {camera_position}"
            )
        d = self.data
        d.mocap_pos[:, 2] = _PARKED_Z
        for t in targets:
            if t.target_id not in self._mocap:
                raise ValueError(f"target {t.target_id} is not in this scene {self.target_ids}")
            k = self._mocap[t.target_id]
            d.mocap_pos[k] = (t.position[0], t.position[1], 0.0)
            d.mocap_quat[k] = _yaw_quat(t.heading)
        d.mocap_pos[self._camera_mocap] = camera_position
        self._cull_trees(camera_position, yaw)
        d.mocap_quat[self._camera_mocap] = _yaw_quat(yaw)
        mujoco.mj_kinematics(self.model, d)
        mujoco.mj_camlight(self.model, d)
        self._renderer.update_scene(d, self._camera_id)
        # Square frame, anisotropic pixels: fix the horizontal half-extent from the HFOV.
        for gl_camera in self._renderer.scene.camera:
            gl_camera.frustum_width = gl_camera.frustum_near * math.tan(
                math.radians(self.camera.hfov_deg) / 2
            )
        return self._renderer.render()

    def _cull_trees(self, camera_position: np.ndarray, yaw: float) -> None:
        """Hide (alpha 0: MuJoCo skips the geom) trees outside the camera's view frustum.

        A canopy top ``canopy_top`` m high is seen up to ``h / (h - canopy_top)`` times farther
        out than the ground footprint; one canopy radius is added as margin. Drawing ~1400
        cylinders costs ~4x the rest of an orchard frame, and a frame shows a small share.
        """
        if self._tree_geoms.size == 0:
            return
        env = self.environment
        height = camera_position[2]
        reach = height / max(height - env.canopy_top, 1e-3)
        half_u, half_v = self.camera.footprint_half_extent(height)
        d = self.model.geom_pos[self._tree_geoms, :2] - camera_position[:2]  # (G, 2)
        cos_y, sin_y = math.cos(yaw), math.sin(yaw)
        u = np.abs(d[:, 0] * cos_y + d[:, 1] * sin_y)
        v = np.abs(d[:, 0] * sin_y - d[:, 1] * cos_y)
        margin = env.canopy_radius + 1.0
        seen = (u <= half_u * reach + margin) & (v <= half_v * reach + margin)
        self.model.geom_rgba[self._tree_geoms, 3] = seen.astype(np.float32)

    def render_view(self, view: CameraView) -> np.ndarray:
        """The frame of ``view`` (its camera pose and targets)."""
        return self.render(view.camera_position, view.yaw, view.targets)

    def close(self) -> None:
        """Free the OpenGL context."""
        self._renderer.close()

    def _scene_xml(self) -> str:
        env = self.environment
        field = env.field
        orchard = env.kind == "orchard"
        ground = _GRASS if orchard else _SOIL
        half_w = field.width / 2 + GROUND_MARGIN
        half_h = field.height / 2 + GROUND_MARGIN
        v = self.vehicle
        vfov = self.camera.vfov_deg
        bodies = [
            f'<body name="drone" mocap="true" pos="0 0 50">'
            f'<camera name="down" mode="fixed" fovy="{vfov:.6f}"/></body>'
        ]
        for i in self.target_ids:
            r, g, b = target_colour(i)
            bodies.append(
                f'<body name="vehicle{i}" mocap="true" pos="0 0 {_PARKED_Z}">'
                f'<geom type="box" size="{v.length / 2} {v.width / 2} {v.height / 2}" '
                f'pos="0 0 {v.height / 2}" rgba="{r} {g} {b} 1" material="paint"/></body>'
            )
        static = [
            f'<geom name="ground" type="plane" size="{half_w} {half_h} 1" '
            f'pos="{field.width / 2} {field.height / 2} 0" material="ground"/>'
        ]
        if env.kind == "crop_field":
            length = field.width - 2 * field.headland
            for y in env.tree_row_y:
                static.append(
                    f'<geom type="box" size="{length / 2} {CROP_WIDTH / 2} {CROP_HEIGHT / 2}" '
                    f'pos="{field.width / 2} {y} {CROP_HEIGHT / 2}" material="crop"/>'
                )
        if orchard:
            rng = np.random.default_rng(0)  # fixed shade variation of the canopies
            half_canopy = (env.canopy_top - env.canopy_bottom) / 2
            for x, y in env.trees:
                shade = rng.uniform(0.8, 1.15)
                r, g, b = 0.16 * shade, 0.38 * shade, 0.12 * shade
                static.append(
                    f'<geom type="cylinder" size="{TRUNK_RADIUS} {env.canopy_bottom / 2}" '
                    f'pos="{x} {y} {env.canopy_bottom / 2}" rgba="0.35 0.24 0.14 1"/>'
                    f'<geom type="cylinder" size="{env.canopy_radius} {half_canopy}" '
                    f'pos="{x} {y} {env.canopy_bottom + half_canopy}" '
                    f'rgba="{r:.3f} {g:.3f} {b:.3f} 1" material="leaves"/>'
                )
        side = self.size_px
        return f"""
<mujoco model="dronefl_{env.kind}">
  <statistic extent="100" center="{field.width / 2} {field.height / 2} 0"/>
  <visual>
    <global offwidth="{side}" offheight="{side}"/>
    <quality shadowsize="0" numslices="8"/>
    <map znear="0.002" zfar="20"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.35 0.35 0.35" specular="0 0 0"/>
  </visual>
  <asset>
    <texture name="ground" type="2d" builtin="flat" width="512" height="512"
             rgb1="{ground[0]}" markrgb="{ground[1]}" mark="random" random="0.25"/>
    <material name="ground" texture="ground" texrepeat="0.05 0.05" texuniform="true"
              reflectance="0" specular="0"/>
    <texture name="crop" type="2d" builtin="flat" width="256" height="256"
             rgb1="0.20 0.50 0.15" markrgb="0.35 0.62 0.20" mark="random" random="0.3"/>
    <material name="crop" texture="crop" texrepeat="0.5 0.5" texuniform="true"
              reflectance="0" specular="0"/>
    <texture name="leaves" type="2d" builtin="flat" width="128" height="128"
             rgb1="1 1 1" markrgb="0.6 0.7 0.5" mark="random" random="0.3"/>
    <material name="leaves" texture="leaves" texrepeat="1 1" texuniform="true"
              reflectance="0" specular="0"/>
    <material name="paint" reflectance="0" specular="0.1"/>
  </asset>
  <worldbody>
    <light directional="true" pos="0 0 100" dir="0.25 0.15 -1" castshadow="false"
           diffuse="0.55 0.55 0.55" specular="0 0 0"/>
    {"".join(static)}
    {"".join(bodies)}
  </worldbody>
</mujoco>"""


def _yaw_quat(yaw: float) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` of a rotation by ``yaw`` rad about world z."""
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
