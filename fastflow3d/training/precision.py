"""``trainer.precision``: ``auto`` (the recipes' value) chosen per host, and a reduced precision asked for by name that
this host would emulate said in one line with its cost.

``auto`` is bf16 autocast (``bf16-mixed``: float32 weights, bf16 convolutions) on a GPU that has bf16 and on a CPU
that computes it natively (``icpflow.core.hardware.native_bf16``: AVX512_BF16, AMX, Arm's bf16, as oneDNN runs it),
float32 (``32-true``) everywhere else: on an AVX2 CPU one bf16 convolution is 50-170x slower than in float32.
"""

from __future__ import annotations

from icpflow.core.hardware import native_bf16

#: Lightning's names of bf16 and float16 training precisions (its ``precision`` argument)
BF16 = ("bf16-mixed", "bf16-true", "bf16", "bf16-mixed-true")
FP16 = ("16-mixed", "16-true", "16", "16-mixed-true")
#: what an emulated half precision costs per convolution against float32 (BENCHMARKS.md, "Every CPU")
EMULATED_COST = "about 50-170x slower per convolution than 32-true"


def on_gpu(accelerator: str) -> bool:
    """Does ``trainer.accelerator`` train on a CUDA GPU here (``gpu``, ``cuda``, or ``auto`` with one present)?"""
    import torch

    if accelerator in ("gpu", "cuda"):
        return True
    return accelerator == "auto" and torch.cuda.is_available()


def choose_precision(requested, accelerator: str, bf16_check=native_bf16, gpu_bf16=None) -> tuple[str, str, bool]:
    """``(precision, line, warn)`` for ``trainer.precision=requested`` on ``trainer.accelerator``: the Lightning
    precision to train in, the line that says it and why, and whether that line is a warning (a half precision asked
    for by name that this host emulates). ``bf16_check`` / ``gpu_bf16``: the CPU's and the GPU's answers (tests)."""
    text = str(requested)
    gpu = on_gpu(str(accelerator))
    if gpu:
        import torch

        has_bf16 = gpu_bf16() if gpu_bf16 else torch.cuda.is_available() and torch.cuda.is_bf16_supported()
        if text == "auto":
            chosen = "bf16-mixed" if has_bf16 else "32-true"
            why = "this GPU has bf16" if has_bf16 else "this GPU has no bf16 (or none is visible)"
            return chosen, f"precision auto: {chosen}, {why}", False
        return text, f"precision {text} (as given)", False
    native, why = bf16_check()
    if text == "auto":
        chosen = "bf16-mixed" if native else "32-true"
        return chosen, f"precision auto: {chosen} on the CPU, {why}", False
    if text in BF16 and not native:
        return text, f"precision {text} as given, but {why}: {EMULATED_COST}; precision=auto picks 32-true here", True
    if text in FP16:
        line = f"precision {text} as given: float16 is emulated on most CPUs, {EMULATED_COST}; precision=auto is "
        return text, line + ("bf16-mixed here" if native else "32-true here"), True
    return text, f"precision {text} (as given)", False
