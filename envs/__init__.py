"""Environments of the OCN reference implementation, registered with gymnasium on import.

Registration is skipped for ids already present, so importing (or reloading) twice is silent.
"""

from gymnasium.envs.registration import register, registry

CRAFT_ENV_IDS = {"OCN/Craft-v0": "paper", "OCN/CraftFull-v0": "full"}

for _env_id, _mode in CRAFT_ENV_IDS.items():
    if _env_id not in registry:
        register(
            id=_env_id,
            entry_point="envs.craft.env:CraftEnv",
            vector_entry_point="envs.craft.env:CraftVectorEnv",
            kwargs={"mode": _mode},
        )
