"""What this host's CPU computes natively, as the engines that run our kernels see it.

Speed-ups from reduced precision exist only where the CPU computes it in hardware: bf16 autocast is 1.4-2.1x faster
than float32 on a CPU with AVX512-BF16 and 50-170x slower on an AVX2 CPU, which emulates it (BENCHMARKS.md, "Every
CPU"). So every reduced-precision choice asks here, and here asks the engine itself where it can tell: oneDNN (torch's
CPU convolutions) reports whether it runs bf16 at all and honours ``ONEDNN_MAX_CPU_ISA``, so a host held to AVX2 with
that switch chooses as an AVX2 host would.

:func:`native_bf16` answers for torch on the CPU, :func:`host_line` names the CPU and the switches in effect for a
benchmark's table. ``/proc/cpuinfo`` is read through :func:`icpflow.core.threads.cpu_fields`.
"""

from __future__ import annotations

import os
import platform

from icpflow.core.threads import cpu_fields

#: oneDNN's ``ONEDNN_MAX_CPU_ISA`` values in its documented order (each includes the ones before it); bf16 is computed
#: natively from ``AVX512_CORE_BF16`` on (``AVX2_VNNI_2`` only converts bf16)
ONEDNN_ISAS = (
    "SSE41",
    "AVX",
    "AVX2",
    "AVX2_VNNI",
    "AVX2_VNNI_2",
    "AVX512_CORE",
    "AVX512_CORE_VNNI",
    "AVX512_CORE_BF16",
    "AVX10_1_512",
    "AVX512_CORE_FP16",
    "AVX10_1_512_AMX",
    "AVX512_CORE_AMX",
    "AVX10_1_512_AMX_FP16",
    "AVX512_CORE_AMX_FP16",
    "AVX10_2_512",
    "AVX10_2_512_AMX_2",
    "ALL",
    "DEFAULT",
)
#: CPU flags (x86 ``flags``, Arm ``Features``) of bf16 arithmetic in hardware
BF16_FLAGS = ("avx512_bf16", "amx_bf16", "bf16")
#: the environment variables that hold an engine to fewer instructions than the CPU has (named in benchmark tables)
ISA_SWITCHES = ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY", "MKL_ENABLE_INSTRUCTIONS", "NUMBA_CPU_NAME")


def cpu_flags(cpuinfo: str | None = None) -> set[str]:
    """The first processor's instruction-set flags (x86 ``flags`` or Arm ``Features`` of ``/proc/cpuinfo``; its text
    ``cpuinfo``, read when None); empty where there is no such file (macOS, Windows)."""
    fields = cpu_fields(cpuinfo)
    return set((fields.get("flags") or fields.get("Features") or "").split())


def onednn_cap(environ=None) -> str | None:
    """The ISA that ``ONEDNN_MAX_CPU_ISA`` holds oneDNN to (upper case), or None when unset; ValueError (one line) for a
    value oneDNN does not know."""
    value = (os.environ if environ is None else environ).get("ONEDNN_MAX_CPU_ISA", "").strip().upper()
    if not value:
        return None
    if value not in ONEDNN_ISAS:
        raise ValueError(f"ONEDNN_MAX_CPU_ISA={value} is not one of oneDNN's ISAs ({', '.join(ONEDNN_ISAS)})")
    return value


def _onednn_bf16() -> bool:
    """oneDNN's own answer: does it run bf16 on this CPU (natively or emulated with AVX-512), under its ISA cap?"""
    import torch

    return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())


def torch_bf16_flags() -> set[str]:
    """The bf16 instruction sets torch's own CPU probe finds (``torch.cpu``'s AVX512-BF16 and AMX checks): the answer
    where there is no ``/proc/cpuinfo`` to read (Windows, macOS)."""
    import torch

    probes = (("avx512_bf16", "_is_avx512_bf16_supported"), ("amx_bf16", "_is_amx_tile_supported"))
    return {flag for flag, probe in probes if getattr(torch.cpu, probe, lambda: False)()}


def native_bf16(
    cpuinfo: str | None = None, environ=None, engine=None, system: str | None = None, probe=None
) -> tuple[bool, str]:
    """Does torch compute bf16 natively on this CPU? ``(answer, reason)``, the reason a phrase for a log line.

    Native means all three: the CPU has bf16 arithmetic (:data:`BF16_FLAGS` in ``/proc/cpuinfo``, else torch's own
    probe, ``probe()`` (:func:`torch_bf16_flags`); a Mac's Apple Silicon is not counted: torch runs no oneDNN there);
    oneDNN runs bf16 (``engine()``, default torch's
    ``_is_mkldnn_bf16_supported``, which honours ``ONEDNN_MAX_CPU_ISA``); and ``ONEDNN_MAX_CPU_ISA``, where set, is at
    or above ``AVX512_CORE_BF16``. An AVX-512 CPU without bf16 instructions passes oneDNN's check (it emulates bf16
    with AVX-512 there) and is refused by the first."""
    flags = cpu_flags(cpuinfo)
    if not flags:
        flags = (probe or torch_bf16_flags)()
        if not flags:
            where = system or platform.system()
            return False, f"no bf16 instructions found ({where}: no /proc/cpuinfo; torch's probe finds none)"
    native = sorted(flag for flag in BF16_FLAGS if flag in flags)
    if not native:
        return False, "this CPU has no bf16 instructions (no AVX512_BF16, AMX or Arm bf16): bf16 would be emulated"
    cap = onednn_cap(environ)
    if cap is not None and ONEDNN_ISAS.index(cap) < ONEDNN_ISAS.index("AVX512_CORE_BF16"):
        return False, f"oneDNN is held to {cap} (ONEDNN_MAX_CPU_ISA), below AVX512_CORE_BF16: bf16 would be emulated"
    if not (engine or _onednn_bf16)():
        return False, "torch's oneDNN does not run bf16 on this CPU"
    return True, f"this CPU computes bf16 natively ({', '.join(native)}; oneDNN runs it)"


def host_line(cpuinfo: str | None = None, environ=None) -> str:
    """One line for a benchmark's table: the CPU's vector instruction sets (AVX2, AVX-512, VNNI, native bf16) and
    every switch in effect that holds an engine below them (:data:`ISA_SWITCHES`)."""
    flags = cpu_flags(cpuinfo)
    environ = os.environ if environ is None else environ
    sets = [
        label
        for label, present in (
            ("AVX2", "avx2" in flags),
            ("AVX-512", "avx512f" in flags),
            ("VNNI", bool({"avx512_vnni", "avx_vnni"} & flags)),
            ("Arm dot products", "asimddp" in flags),
            ("bf16", bool(set(BF16_FLAGS) & flags)),
            ("AMX", "amx_tile" in flags),
        )
        if present
    ]
    switches = [f"{name}={environ[name]}" for name in ISA_SWITCHES if environ.get(name)]
    held = f"; held by {' '.join(switches)}" if switches else ""
    return f"instruction sets: {', '.join(sets) or ('no AVX2' if flags else 'unknown')}{held}"
