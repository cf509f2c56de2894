"""Precision chosen per host: what the CPU computes natively (``icpflow.core.hardware``, as oneDNN sees it, its
``ONEDNN_MAX_CPU_ISA`` switch honoured) and ``trainer.precision: auto`` (``fastflow3d.training.precision``): bf16
autocast only where it is native, float32 elsewhere, a precision asked for by name that this host emulates said in one
line with its cost; every recipe says ``auto``."""

import json
import logging
import subprocess
import sys

import pytest
import torch

from fastflow3d.training.precision import choose_precision
from fastflow3d.training.trainer import fit
from icpflow.core.hardware import host_line, native_bf16, onednn_cap
from icpflow.datasets.synthetic.reader import SyntheticDataset

from helpers.shards import write_pseudo_labels
from helpers.training import CONF
from helpers.training import compose_train as _compose
from helpers.training import train_cfg as _cfg

AVX2_HOST = "processor\t: 0\nflags\t\t: fpu sse2 avx fma avx2 bmi2\n"  # Zen 3: AVX2, no AVX-512, VNNI or bf16
AVX512_HOST = "processor\t: 0\nflags\t\t: avx2 avx512f avx512bw avx512_vnni\n"  # Cascade Lake: no bf16
BF16_HOST = "processor\t: 0\nflags\t\t: avx2 avx512f avx512_vnni avx512_bf16\n"  # Zen 4/5, Cooper Lake
ARM_BF16 = "processor\t: 0\nFeatures\t: fp asimd asimddp bf16\n"


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    dataset = SyntheticDataset(split="test", beams=32, num_sequences=1, frames_per_sequence=2, seed=0)
    return write_pseudo_labels(tmp_path_factory.mktemp("shards"), [dataset[0]])


def yes():
    return True


def no():
    return False


@pytest.mark.parametrize(
    "cpuinfo, environ, engine, native, reason",
    [
        (BF16_HOST, {}, yes, True, "computes bf16 natively (avx512_bf16"),
        (ARM_BF16, {}, yes, True, "natively (bf16"),
        (AVX2_HOST, {}, yes, False, "no bf16 instructions"),
        (AVX512_HOST, {}, yes, False, "no bf16 instructions"),  # oneDNN would run it, emulated with AVX-512
        (BF16_HOST, {"ONEDNN_MAX_CPU_ISA": "AVX2"}, yes, False, "held to AVX2 (ONEDNN_MAX_CPU_ISA)"),
        (BF16_HOST, {"ONEDNN_MAX_CPU_ISA": "avx512_core"}, yes, False, "held to AVX512_CORE"),
        (BF16_HOST, {"ONEDNN_MAX_CPU_ISA": "AVX512_CORE_BF16"}, yes, True, "natively"),
        (BF16_HOST, {"ONEDNN_MAX_CPU_ISA": "ALL"}, yes, True, "natively"),
        (BF16_HOST, {}, no, False, "oneDNN does not run bf16"),
    ],
)
def test_native_bf16_needs_the_instructions_and_onednn_under_its_cap(cpuinfo, environ, engine, native, reason):
    answer, why = native_bf16(cpuinfo, environ, engine, system="Linux")
    assert answer is native and reason in why


def test_without_cpuinfo_torchs_own_probe_answers():
    """Windows and macOS have no ``/proc/cpuinfo``: torch's CPU probe names the bf16 instructions there."""
    assert native_bf16("", {}, yes, "Windows", probe=lambda: {"avx512_bf16"}) == (
        True,
        "this CPU computes bf16 natively (avx512_bf16; oneDNN runs it)",
    )
    answer, why = native_bf16("", {"ONEDNN_MAX_CPU_ISA": "AVX2"}, yes, "Windows", probe=lambda: {"amx_bf16"})
    assert not answer and "held to AVX2" in why
    answer, why = native_bf16("", {}, yes, "Darwin", probe=set)
    assert not answer and "no bf16 instructions found (Darwin: no /proc/cpuinfo" in why


def test_an_unknown_onednn_isa_is_one_line():
    with pytest.raises(ValueError, match="ONEDNN_MAX_CPU_ISA=AVX3 is not one of oneDNN's ISAs"):
        onednn_cap({"ONEDNN_MAX_CPU_ISA": "avx3"})


def test_torchs_onednn_honours_the_avx2_switch_on_any_host():
    """On a host held to AVX2, oneDNN itself says it runs no bf16, and ``native_bf16`` agrees, whatever the CPU: the
    switch is read when torch is imported, so in a fresh process."""
    code = (
        "import json, torch; from icpflow.core.hardware import native_bf16; "
        "print(json.dumps([bool(torch.ops.mkldnn._is_mkldnn_bf16_supported()), native_bf16()[0]]))"
    )
    env = {"ONEDNN_MAX_CPU_ISA": "AVX2", "PATH": "/usr/bin:/bin"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert json.loads(done.stdout.strip().splitlines()[-1]) == [False, False]


def test_choose_precision_per_host():
    native, emulated = (lambda: (True, "native")), (lambda: (False, "this CPU has no bf16 instructions"))
    chosen = choose_precision("auto", "cpu", native)
    assert chosen == ("bf16-mixed", "precision auto: bf16-mixed on the CPU, native", False)
    assert choose_precision("auto", "cpu", emulated)[:2] == (
        "32-true",
        "precision auto: 32-true on the CPU, this CPU has no bf16 instructions",
    )
    precision, line, warn = choose_precision("bf16-mixed", "cpu", emulated)
    assert precision == "bf16-mixed" and warn  # as asked, but said with what it costs
    assert "about 50-170x slower per convolution than 32-true" in line and "precision=auto picks 32-true" in line
    assert choose_precision("bf16-mixed", "cpu", native) == ("bf16-mixed", "precision bf16-mixed (as given)", False)
    assert choose_precision("16-mixed", "cpu", native)[2]
    assert "float16 is emulated" in choose_precision(16, "cpu", emulated)[1]
    assert choose_precision("32-true", "cpu", emulated) == ("32-true", "precision 32-true (as given)", False)
    assert choose_precision("auto", "gpu", emulated, gpu_bf16=yes)[0] == "bf16-mixed"
    assert choose_precision("auto", "gpu", native, gpu_bf16=no)[:2] == (
        "32-true",
        "precision auto: 32-true, this GPU has no bf16 (or none is visible)",
    )


def test_every_recipe_and_trainer_says_auto():
    """No recipe hard-codes a precision: ``python train.py`` and every experiment and trainer group say auto."""
    experiments = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
    trainers = sorted(p.stem for p in (CONF / "trainer").glob("*.yaml"))
    assert _compose().trainer.precision == "auto"
    for experiment in experiments:
        assert _compose(f"experiment={experiment}").trainer.precision == "auto", experiment
    for trainer in trainers:
        assert _compose(f"trainer={trainer}").trainer.precision == "auto", trainer


def test_a_run_says_the_precision_auto_chose_and_its_checkpoint_keeps_it(shards, tmp_path, monkeypatch, caplog):
    """Held to AVX2 (``ONEDNN_MAX_CPU_ISA``), ``precision: auto`` trains in float32 on any host, says so in its first
    lines and saves the precision it trained in; bf16 asked for by name there is a warning that names its cost."""
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    base = ("trainer.max_steps=1", "trainer.num_sanity_val_steps=0", "export.formats=[]", "trainer.precision=auto")
    with caplog.at_level(logging.INFO, logger="fastflow3d.training"):
        trainer = fit(_cfg(tmp_path, shards, shards, *base))
    assert str(trainer.precision) == "32-true"
    assert "precision auto: 32-true on the CPU, oneDNN is held to AVX2 (ONEDNN_MAX_CPU_ISA)" in caplog.text
    saved = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)
    assert saved["hyper_parameters"]["cfg"]["trainer"]["precision"] == "32-true"
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="fastflow3d.training"):
        cfg = _cfg(tmp_path / "b", shards, shards, *base[:3], "trainer.precision=bf16-mixed")
        assert str(fit(cfg).precision) == "bf16-mixed"
    assert "precision bf16-mixed as given, but oneDNN is held to AVX2" in caplog.text and "50-170x" in caplog.text


def test_host_line_names_the_instruction_sets_and_the_switches_in_effect():
    assert host_line(BF16_HOST, {}) == "instruction sets: AVX2, AVX-512, VNNI, bf16"
    assert host_line(AVX2_HOST, {"ONEDNN_MAX_CPU_ISA": "AVX2", "NUMBA_CPU_NAME": "haswell"}) == (
        "instruction sets: AVX2; held by ONEDNN_MAX_CPU_ISA=AVX2 NUMBA_CPU_NAME=haswell"
    )
    assert host_line("", {}) == "instruction sets: unknown"
