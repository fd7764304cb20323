"""The evaluation job: the metric suite on checkpoints, run apart from training.

Owns the job (``job``: claims, watching a run, one result per checkpoint and sampling point), its typed config and
protocols (``config``), replications and generation for the T2M protocol (``replications``), evaluator embedding
spaces (``spaces``), FlowMDM's composition protocol (``composition``), the results store and plots (``store``,
``plots``) and the training of our own contrastive evaluator (``evaluator_training``). May import the shared
modules, pipeline.data, pipeline.generation and mfm; nothing in pipeline/ imports it.
"""
