"""Export a trained FastFlow3D checkpoint for inference outside this code base (see conf/export.yaml and
fastflow3d.artifact.export): ONNX (ONNX Runtime) and/or a torch.export program (.pt2) with dynamic point counts, plus
metadata.json. The same as the console script ``fastflow3d-export`` (``fastflow3d.training.cli.export_main``).
``--help``: the options, ``--cfg job``: the whole config.

    python export.py checkpoint=<path.ckpt> [format=onnx|pt2|all] [out_dir=<dir>]
"""

from fastflow3d.training.launch import export_main

if __name__ == "__main__":
    export_main()
