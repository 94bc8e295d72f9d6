"""Environments of the OCN reference implementation, registered with gymnasium on import.

Registration is skipped for ids already present, so importing (or reloading) twice is silent.
`OCN/CraftLeRobot-v0` and `OCN/DialLeRobot-v0` are Craft and Dial shaped for `lerobot-eval` (see
lerobot_policy_ocn.envs.lerobot_env); entry points are imported only when an env is made, so registering them imports
neither LeRobot nor MuJoCo. `OCN/BabyAI-OpenPickupSeq-v0` is registered where minigrid (the optional
`babyai` extra) is importable, by `lerobot_policy_ocn.envs.babyai`, imported here; that package finds
minigrid without importing it.
"""

from gymnasium.envs.registration import register, registry

from lerobot_policy_ocn.envs.babyai import BABYAI_ENV_ID  # noqa: F401  (a re-export; importing registers it)

CRAFT_ENV_IDS = {"OCN/Craft-v0": "paper", "OCN/CraftFull-v0": "full"}
CRAFT_LEROBOT_ENV_ID = "OCN/CraftLeRobot-v0"
DIAL_ENV_ID = "OCN/Dial-v0"
DIAL_LEROBOT_ENV_ID = "OCN/DialLeRobot-v0"

for _env_id, _mode in CRAFT_ENV_IDS.items():
    if _env_id not in registry:
        register(
            id=_env_id,
            entry_point="lerobot_policy_ocn.envs.craft.env:CraftEnv",
            vector_entry_point="lerobot_policy_ocn.envs.craft.env:CraftVectorEnv",
            kwargs={"mode": _mode},
        )

if CRAFT_LEROBOT_ENV_ID not in registry:
    register(id=CRAFT_LEROBOT_ENV_ID, entry_point="lerobot_policy_ocn.envs.craft.lerobot_env:make_lerobot_craft_env")

if DIAL_ENV_ID not in registry:
    register(id=DIAL_ENV_ID, entry_point="lerobot_policy_ocn.envs.dial.env:DialEnv",
             vector_entry_point="lerobot_policy_ocn.envs.dial.env:DialVectorEnv")

if DIAL_LEROBOT_ENV_ID not in registry:
    register(id=DIAL_LEROBOT_ENV_ID, entry_point="lerobot_policy_ocn.envs.dial.lerobot_env:make_lerobot_dial_env")
