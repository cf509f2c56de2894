"""Evaluate scene-flow methods against ground truth (see conf/eval.yaml and icpflow.evaluation); the student comes
from fastflow3d.inference.eval_methods.

    python eval.py [dataset=<name>] [split=val]
        [method=[zero,ego,icpflow,icpflow-raw,student,student+refine,student-stream,student-stream+refine,shards]]
        [checkpoint=...]
        [shards=<label out_dir>] [horizon=k | horizon=[1,2,3,4] | horizon=1..4] [tracker=true | tracker=[false,true]]
        [limit=N] [bev=N] [render=N] [out_dir=...]

Several horizons give the long-horizon table (EPE against the time gap, one row per method and horizon).
"""

import sys

import hydra
from omegaconf import DictConfig

from fastflow3d.inference.eval_methods import (
    refined_streamed_student_method,
    refined_student_method,
    streamed_student_method,
    student_method,
)
from icpflow.console import quiet
from icpflow.errors_and_signals import reported, run
from icpflow.evaluation import run_eval
from icpflow.options import register

register()  # eval_schema in Hydra's ConfigStore: the structured config conf/eval.yaml extends


@hydra.main(version_base="1.3", config_path="conf", config_name="eval")
def main(cfg: DictConfig) -> None:
    quiet()
    with reported("eval"):
        methods = {
            "student": student_method,
            "student+refine": refined_student_method,
            "student-stream": streamed_student_method,  # nothing given: the stream's ego motion and ground
            "student-stream+refine": refined_streamed_student_method,  # the same, refined (fastflow3d-infer --refine)
        }
        status = run_eval(cfg, extra_methods=methods)
        if status:
            sys.exit(status)


if __name__ == "__main__":
    run("eval", main)
