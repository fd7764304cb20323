"""The generation job: motions from a checkpoint.

A request (``request``: the typed SampleRequest, its flags and YAML) is run once by ``sampling`` (text- and
action-to-motion, edits) or by ``composing`` (FlowMDM composition, extrapolation); both load and integrate the
checkpoint through ``inference`` (a trained model and its data identity) and ``integration`` (solver or sampler,
noise seeds), and write through ``outputs`` (sample files, results.json, index.html via ``browse``). Also the
exported-folder API (``pretrained``) and contact sheets (``contact_sheet``). May import the shared modules,
pipeline.data and mfm; pipeline.evaluation imports it, training does not.
"""
