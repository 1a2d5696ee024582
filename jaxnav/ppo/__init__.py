"""PPO components: actor-critic networks, observation normalisation and losses."""
