"""Acting in the worlds: batched rollouts, PPO over frozen options, OMPN's RL form."""
