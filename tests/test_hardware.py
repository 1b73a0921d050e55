"""bf16 only where the hardware runs it: the CPU's bfloat16 units read from /proc/cpuinfo, a
bf16 run refused in one line on a CPU without them, and precision=auto's choice."""

from __future__ import annotations

import json

import pytest

from hmepol_cli import hardware, precision
from hmepol_cli.config import check_precision
from hmepol_cli.errors import ConfigError
from tests.test_bad_input import assert_one_line, run
from tests.test_cli import TINY, hmepol

AVX2_EPYC = """processor\t: 0
vendor_id\t: AuthenticAMD
model name\t: AMD EPYC 7B13
flags\t\t: fpu sse sse2 avx avx2 fma bmi2
"""
BF16_XEON = """processor\t: 0
model name\t: Intel(R) Xeon(R) Platinum 8480C
flags\t\t: fpu avx2 avx512f avx512bw avx512_bf16 amx_bf16 amx_tile
"""
NEOVERSE = """processor\t: 0
BogoMIPS\t: 2100.00
Features\t: fp asimd evtstrm aes sve bf16 i8mm
"""


# what reads /proc/cpuinfo once and keeps it
CACHED = (hardware.cpu_name, hardware.cpu_model, hardware.cpu_flags, precision.auto_precision)


@pytest.fixture
def cpu(tmp_path, monkeypatch):
    """Pretend /proc/cpuinfo reads ``text``; the caches forget the real one."""

    def pretend(text: str) -> None:
        path = tmp_path / "cpuinfo"
        path.write_text(text)
        monkeypatch.setattr(hardware, "CPUINFO", path)
        for cached in CACHED:
            cached.cache_clear()

    yield pretend
    for cached in CACHED:
        cached.cache_clear()


GENERIC_XEON = """processor\t: 0
vendor_id\t: GenuineIntel
cpu family\t: 6
model\t\t: 167
model name\t: Intel(R) Xeon(R) Processor
flags\t\t: fpu avx2 avx512f
processor\t: 1
vendor_id\t: GenuineIntel
cpu family\t: 6
model\t\t: 167
model name\t: Intel(R) Xeon(R) Processor
"""


@pytest.mark.parametrize(
    "text, model",
    [
        # a virtual machine's generic name: the family and model numbers tell its CPUs apart
        (GENERIC_XEON, "Intel(R) Xeon(R) Processor (family 6, model 167)"),
        (AVX2_EPYC, "AMD EPYC 7B13"),  # no numbers listed: the name alone
        (NEOVERSE, "aarch64"),
    ],
)
def test_the_cpu_model_run_json_records_names_family_and_model(cpu, monkeypatch, text, model):
    monkeypatch.setattr(hardware.platform, "processor", lambda: "")
    monkeypatch.setattr(hardware.platform, "machine", lambda: "aarch64")
    cpu(text)
    assert hardware.cpu_model() == model


@pytest.mark.parametrize(
    "text, name, units",
    [
        (AVX2_EPYC, "AMD EPYC 7B13", []),
        (BF16_XEON, "Intel(R) Xeon(R) Platinum 8480C", ["avx512_bf16", "amx_bf16"]),
        (NEOVERSE, "aarch64", ["bf16"]),  # Arm lists no model name: the platform's word
    ],
)
def test_the_cpu_and_its_bfloat16_units_are_read_from_cpuinfo(cpu, monkeypatch, text, name, units):
    monkeypatch.setattr(hardware.platform, "processor", lambda: "")
    monkeypatch.setattr(hardware.platform, "machine", lambda: "aarch64")
    cpu(text)
    assert hardware.cpu_name() == name
    assert hardware.bfloat16_units() == units
    assert ("no bfloat16 units" in hardware.describe_cpu()) == (not units)


def test_bf16_on_a_cpu_without_bfloat16_units_is_refused_in_one_line(cpu, tmp_path, capsys):
    cpu(AVX2_EPYC)
    run_dir = tmp_path / "run"
    code, text = run(capsys, "train", "precision=bf16", f"hydra.run.dir={run_dir}")
    assert_one_line(code, text, "bfloat16 units")
    assert "AMD EPYC 7B13" in text and "use precision=float32" in text
    assert not run_dir.exists()


def test_bf16_on_a_cpu_with_bfloat16_units_passes_the_check(cpu):
    cpu(BF16_XEON)
    check_precision("bf16", "cpu")  # no refusal
    cpu(AVX2_EPYC)
    with pytest.raises(ConfigError, match="bfloat16 units"):
        check_precision("bf16", "cpu")


@pytest.mark.parametrize(
    "text, speedup, chosen",
    [(AVX2_EPYC, 50.0, "float32"), (BF16_XEON, 2.0, "bf16"), (BF16_XEON, 1.1, "float32")],
)
def test_precision_auto_picks_bf16_only_where_it_has_units_and_measures_faster(
    cpu, monkeypatch, text, speedup, chosen
):
    cpu(text)
    measured = []
    monkeypatch.setattr(
        hardware, "bf16_speedup", lambda device: measured.append(device) or speedup
    )
    from omegaconf import OmegaConf

    assert precision.precision_of(OmegaConf.create({"precision": "auto"})).name == chosen
    # Without units nothing is measured (bf16 products would take seconds on the slow path).
    assert measured == ([] if text == AVX2_EPYC else ["cpu"])
    check_precision("auto", "cpu")


def test_the_bf16_speedup_is_a_measured_ratio():
    ratio = hardware.bf16_speedup("cpu", rows=64, width=16)
    assert 0 < ratio < float("inf")


@pytest.mark.parametrize(
    "text, speedup, chosen, why",
    [
        (AVX2_EPYC, 50.0, "float32", "this cpu has no bfloat16 arithmetic"),
        (BF16_XEON, 2.0, "bf16", "a hidden layer's bf16 products measured 2.00x float32's"),
        (BF16_XEON, 1.1, "float32", "a hidden layer's bf16 products measured 1.10x float32's"),
    ],
)
def test_precision_auto_says_what_it_chose_and_why(cpu, monkeypatch, text, speedup, chosen, why):
    cpu(text)
    monkeypatch.setattr(hardware, "bf16_speedup", lambda device: speedup)
    assert precision.auto_reason("cpu").startswith(f"precision=auto chose {chosen}: {why}")


@pytest.mark.slow
def test_a_run_with_precision_auto_says_its_choice_and_records_it(tmp_path):
    """Whatever this machine chooses, the run says it as it starts and run.json keeps it."""
    run_dir = tmp_path / "run"
    proc = hmepol("train", *TINY, "env=corridor", "algo=mepol", "epochs=1", "precision=auto",
                  f"hydra.run.dir={run_dir}", cwd=tmp_path)  # fmt: skip
    chosen = json.loads((run_dir / "run.json").read_text())["precision"]
    assert chosen in ("float32", "bf16")
    assert f"hmepol: precision=auto chose {chosen}: " in proc.stdout
