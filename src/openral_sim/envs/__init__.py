"""Environment adapters, one module each, found through the ``openral.sim_envs`` entry-point group."""
