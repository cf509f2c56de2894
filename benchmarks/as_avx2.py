"""Run a benchmark as on an AVX2 host without AVX-512, VNNI or native bf16, on a host that has them.

    python -m benchmarks.as_avx2 bench_teacher --repeats 5
    python -m benchmarks.as_avx2 bench_training_step --train <shards> --val <shards> --run after=.

The benchmark runs in a fresh process with each engine's documented switch set (:data:`AVX2_SWITCHES`): oneDNN
(torch's convolutions; checked here to take effect: oneDNN then reports no bf16), ATen's vectorised kernels, MKL's
BLAS, and numba's code generation (its kernels compile once more for that CPU, about a minute). ONNX Runtime has no
such switch: it picks its kernels from CPUID, so its networks (the stream's, the CLI's) still run with this host's
AVX-512 and VNNI, and their figures here are not an AVX2 host's (``--precision f32`` at least keeps VNNI out).
The benchmark's table names the switches in effect (``benchmarks.common.cpu_name``). Timings are a lower bound of a
real AVX2 laptop's: clock, caches and memory differ (BENCHMARKS.md, "Every CPU").
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

#: the environment that holds every engine that has a switch to AVX2
AVX2_SWITCHES = {
    "ONEDNN_MAX_CPU_ISA": "AVX2",
    "ATEN_CPU_CAPABILITY": "avx2",
    "MKL_ENABLE_INSTRUCTIONS": "AVX2",
    "NUMBA_CPU_NAME": "haswell",
}


def held_engines(env: dict) -> dict:
    """What torch reports in a process with ``env``: its ATen capability and whether oneDNN runs bf16."""
    code = (
        "import json, torch; print(json.dumps({'aten': torch.backends.cpu.get_cpu_capability(), "
        "'onednn_bf16': bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())}))"
    )
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    if len(sys.argv) < 2 or sys.argv[1].startswith("-"):
        raise SystemExit("usage: python -m benchmarks.as_avx2 <benchmark module> [its arguments]")
    env = {**os.environ, **AVX2_SWITCHES}
    seen = held_engines(env)
    if seen["aten"] != "AVX2" or seen["onednn_bf16"]:
        raise SystemExit(f"as_avx2: the switches did not take effect here: torch reports {seen}")
    switches = " ".join(f"{key}={value}" for key, value in AVX2_SWITCHES.items())
    print(f"as_avx2: {switches} (torch: ATen {seen['aten']}, oneDNN without bf16; ONNX Runtime not held)", flush=True)
    name = sys.argv[1].removeprefix("benchmarks.")
    sys.exit(subprocess.run([sys.executable, "-m", f"benchmarks.{name}", *sys.argv[2:]], env=env).returncode)


if __name__ == "__main__":
    main()
