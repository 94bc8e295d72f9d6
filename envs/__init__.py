"""Environments of the OCN reference implementation, registered with gymnasium on import.

Registration is skipped for ids already present, so importing (or reloading) twice is silent.
`OCN/CraftLeRobot-v0` is Craft shaped for `lerobot-eval` (see envs.craft.lerobot_env); its entry
point is imported only when it is made, so registering it does not import LeRobot.
"""

from gymnasium.envs.registration import register, registry

CRAFT_ENV_IDS = {"OCN/Craft-v0": "paper", "OCN/CraftFull-v0": "full"}
CRAFT_LEROBOT_ENV_ID = "OCN/CraftLeRobot-v0"

for _env_id, _mode in CRAFT_ENV_IDS.items():
    if _env_id not in registry:
        register(
            id=_env_id,
            entry_point="envs.craft.env:CraftEnv",
            vector_entry_point="envs.craft.env:CraftVectorEnv",
            kwargs={"mode": _mode},
        )

if CRAFT_LEROBOT_ENV_ID not in registry:
    register(id=CRAFT_LEROBOT_ENV_ID, entry_point="envs.craft.lerobot_env:make_lerobot_craft_env")
