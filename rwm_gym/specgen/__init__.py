"""Task specs written by a tool (`rwm-gym spec`): from a dm_control suite task or from a legged robot's MJCF.

`from_dmc.dmc_draft` and `from_mjcf.legged_draft` derive a draft spec from the model; `draft.fill_normalization`
measures its normalisation from a short random collection; `command` is the CLI that ties them together.
"""
