"""Physics environments: MuJoCo (and dm_control) simulations that produce data and judge policies."""
