"""A trained FastFlow3D on raw scans: the Predictor (``predictor``; its scan steps ``scan_steps``, its model opened by
``model_loading``, its results ``prediction``), the opt-in refinement (``refine``), the stream (``stream``), the
``fastflow3d-infer`` command (``cli``, ``scan_files``, ``stream_folder``) and the student as an evaluation method
(``eval_methods``; ``eval_cli``: ``fastflow3d-eval``). Imports ``fastflow3d.network`` and ``fastflow3d.artifact``,
never ``fastflow3d.training``."""
