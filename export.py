"""Export a trained FastFlow3D checkpoint for inference outside this code base (see conf/export.yaml and
fastflow3d.artifact.export): ONNX (ONNX Runtime) and/or a torch.export program (.pt2) with dynamic point counts, plus
metadata.json.

    python export.py checkpoint=<path.ckpt> [format=onnx|pt2|all] [out_dir=<dir>]
"""

import sys

import hydra
from omegaconf import DictConfig

from fastflow3d.artifact.export import run_export
from fastflow3d.training.options import register
from icpflow.console import quiet
from icpflow.errors_and_signals import reported, run

register()  # export_schema in Hydra's ConfigStore: the structured config conf/export.yaml extends


@hydra.main(version_base="1.3", config_path="conf", config_name="export")
def main(cfg: DictConfig) -> None:
    quiet()
    with reported("export"):
        status = run_export(cfg)
        if status:
            sys.exit(status)


if __name__ == "__main__":
    run("export", main)
