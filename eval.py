"""Evaluate scene-flow methods against ground truth (see conf/eval.yaml and icpflow.evaluation); the student comes
from fastflow3d.inference.eval_methods. The same as the console script ``fastflow3d-eval``
(``fastflow3d.inference.eval_cli.main``). ``--help``: the options, ``--cfg job``: the whole config.

    python eval.py [dataset=<name>] [split=val]
        [method=[zero,ego,icpflow,icpflow-raw,student,student+refine,student-stream,student-stream+refine,shards]]
        [checkpoint=...]
        [shards=<label out_dir>] [horizon=k | horizon=[1,2,3,4] | horizon=1..4] [tracker=true | tracker=[false,true]]
        [limit=N] [bev=N] [render=N] [out_dir=...]

Several horizons give the long-horizon table (EPE against the time gap, one row per method and horizon).
"""

from fastflow3d.inference.launch import eval_main

if __name__ == "__main__":
    eval_main()
