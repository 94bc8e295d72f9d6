"""The Dial scene: a Kinova JACO arm with its three-finger hand in front of a 10-key pad.

The arm and hand come from the MJCF files (and decimated meshes) that the `dm-control` package
ships under `dm_control/third_party/kinova/`; they are read from the installed package with
`mujoco.MjSpec`, never copied here, and no dm_control Python module is imported. The hand is
attached at the arm's `wristsite`, as dm_control attaches it.

Pad (keys are static boxes the hand can touch; their top faces are the press points). Columns run
along x (away from the arm base), rows along y; the digits are laid out like a phone pad, read by
someone standing on the +y side of the pad looking towards -y:

    y = +0.21 :  1  2  3        x = 0.36, 0.50, 0.64 (columns 1, 2, 3)
    y = +0.07 :  4  5  6
    y = -0.07 :  7  8  9
    y = -0.21 :  .  0  .

The fingertip site sits on the hand's axis where the closed fingers meet (0.2 m below the hand
frame), so it is a hand point independent of the finger joints. Nine torque motors drive the six
arm joints and three finger joints with gears (50, 100, 100, 50, 50, 50, 10, 10, 10) from a
control in [-1, 1]. A `framepos` sensor reports the fingertip position.
"""

from __future__ import annotations

import functools
from importlib import resources
from pathlib import Path

import mujoco
import numpy as np

N_KEYS = 10
PAD_CENTER = np.array([0.5, 0.0, 0.05])
COLUMN_X = (-0.14, 0.0, 0.14)
ROW_Y = (0.21, 0.07, -0.07, -0.21)
# (row, column) of each digit 0-9 on the phone-pad layout above.
DIGIT_CELLS = ((3, 1), (0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2), (2, 0), (2, 1), (2, 2))
KEY_HALF_SIZE = (0.05, 0.05, 0.01)

ARM_JOINTS = ("joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6")
FINGER_JOINTS = ("hand_finger_1", "hand_finger_2", "hand_finger_3")
JOINTS = ARM_JOINTS + FINGER_JOINTS
N_JOINTS = len(JOINTS)
N_ARM_JOINTS = len(ARM_JOINTS)
GEARS = (50.0, 100.0, 100.0, 50.0, 50.0, 50.0, 10.0, 10.0, 10.0)
# Viscous damping (N m s / rad) on the arm joints, as heavy as a geared motor's: the bare model has
# almost none (0.01). About 2 x 12 rad/s x each joint's inertia at the home pose (4.4, 4.5, 4.1, 2.0,
# 2.0, 2.0 kg m^2), so the expert's spring of 12 rad/s stops near critically damped with no velocity
# feedback: the observation holds no velocities (`lerobot_policy_ocn.envs.dial.expert`).
ARM_DAMPING = (100.0, 100.0, 100.0, 50.0, 50.0, 50.0)
FINGERTIP_OFFSET = (0.0, 0.0, -0.2)
FINGERTIP_SITE = "fingertip"
FINGERTIP_SENSOR = "fingertip_pos"
CAMERA = "overview"
CAMERA_POS = np.array([1.2, 0.75, 0.8])
CAMERA_TARGET = np.array([0.4, 0.0, 0.2])
TIMESTEP = 0.002


def kinova_dir() -> Path:
    """Folder of the JACO MJCF files inside the installed dm-control distribution."""
    spec = resources.files("dm_control")
    path = Path(str(spec)) / "third_party" / "kinova"
    if not (path / "jaco_arm.xml").is_file():
        raise FileNotFoundError(f"dm-control is installed but has no Kinova JACO model at {path}")
    return path


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera `xyaxes` (right, then up) of a camera at `eye` looking at `target`, horizon level."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return np.concatenate([right, np.cross(right, forward)])


def key_positions() -> np.ndarray:
    """Press point (top-face centre) of each digit's key, (10, 3), indexed by digit."""
    cells = np.array(DIGIT_CELLS)
    x = PAD_CENTER[0] + np.array(COLUMN_X)[cells[:, 1]]
    y = PAD_CENTER[1] + np.array(ROW_Y)[cells[:, 0]]
    return np.stack([x, y, np.full(N_KEYS, PAD_CENTER[2])], axis=1)


def _add_pad(spec: mujoco.MjSpec) -> None:
    """Static pad body: a slab and ten keys (boxes with a press-point site on top)."""
    spec.add_material(name="key", rgba=[0.85, 0.85, 0.8, 1])
    spec.add_material(name="pad", rgba=[0.2, 0.3, 0.45, 1])
    pad = spec.worldbody.add_body(name="pad", pos=list(PAD_CENTER))
    pad.add_geom(
        name="pad_base", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.23, 0.3, 0.01], pos=[0, 0, -0.03], material="pad"
    )
    half = np.array(KEY_HALF_SIZE)
    for digit, point in enumerate(key_positions()):
        local = point - PAD_CENTER
        pad.add_geom(
            name=f"key_{digit}", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(half),
            pos=list(local - [0, 0, half[2]]), material="key",
        )
        pad.add_site(name=f"key_{digit}", pos=list(local), size=[0.008, 0, 0], rgba=[0.1, 0.1, 0.1, 1])


def build_spec() -> mujoco.MjSpec:
    """The whole Dial scene as an editable MjSpec (arm, hand, pad, floor, motors, camera)."""
    folder = kinova_dir()
    arm = mujoco.MjSpec.from_file(str(folder / "jaco_arm.xml"))
    hand = mujoco.MjSpec.from_file(str(folder / "jaco_hand.xml"))
    arm.attach(hand, site=arm.site("wristsite"), prefix="hand_")
    arm.modelname = "dial"
    arm.option.timestep = TIMESTEP
    for name, damping in zip(ARM_JOINTS, ARM_DAMPING, strict=True):
        arm.joint(name).damping[0] = damping
    arm.body("hand_hand").add_site(name=FINGERTIP_SITE, pos=list(FINGERTIP_OFFSET), size=[0.01, 0, 0])
    world = arm.worldbody
    world.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[1.5, 1.5, 0.05], rgba=[0.5, 0.5, 0.5, 1])
    arm.visual.headlight.ambient = [0.4, 0.4, 0.4]
    world.add_light(name="sun", pos=[0.5, 0, 2.0], dir=[0, 0, -1], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
    world.add_camera(name=CAMERA, pos=list(CAMERA_POS), xyaxes=list(_look_at(CAMERA_POS, CAMERA_TARGET)))
    _add_pad(arm)
    for name, gear in zip(JOINTS, GEARS, strict=True):
        arm.add_actuator(
            name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT, gear=[gear, 0, 0, 0, 0, 0],
            ctrllimited=True, ctrlrange=[-1.0, 1.0],
        )
    arm.add_sensor(
        name=FINGERTIP_SENSOR, type=mujoco.mjtSensor.mjSENS_FRAMEPOS, objtype=mujoco.mjtObj.mjOBJ_SITE,
        objname=FINGERTIP_SITE,
    )
    return arm


@functools.cache
def dial_model() -> mujoco.MjModel:
    """The compiled scene, built once per process and shared (read-only) by every env."""
    return build_spec().compile()

