"""Settings.device: where selections and training run. On a machine without CUDA the setting
is refused naming the field; with CUDA, a session trains and selects there while its record
stays in host memory."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import call, create, make_core, wait_idle
from pydantic import ValidationError

from agilegs.service.serve import SettingError, check_settings
from agilegs.service.settings import Settings


def test_a_device_is_cpu_or_a_cuda_device() -> None:
    assert Settings().device == "cpu"
    with pytest.raises(ValidationError, match="device"):
        Settings(device="gpu")
    with pytest.raises(ValidationError, match="device"):
        Settings(device="cuda:x")


def test_cuda_on_a_machine_without_it_is_refused() -> None:
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(SettingError, match=r"^device: 'cuda': CUDA is not available"):
        check_settings(Settings(device="cuda"))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_session_trains_and_selects_on_the_gpu(tmp_path: Path) -> None:
    core = make_core(tmp_path / "state", device="cuda")
    try:
        create(core)
        st = wait_idle(core)
        assert st.mapper.state == "idle" and st.mapper.steps == 60
        for method in ("agile", "agile_plus", "full_eig"):
            out = call(core, "select", "s", {"method": method, "commit": True})
            assert out.chosen.id >= 0
        rec = core.sessions["s"].record
        assert rec.gmap.means.device.type == "cpu"
        assert all(v.device.type == "cpu" for v in rec.h_acc.values())
    finally:
        core.close()
