import pytest
import torch

from shared.training import resolve_device


def test_auto_takes_cuda_only_when_present():
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto").type == expected
    assert resolve_device("cpu").type == "cpu"


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_asking_for_cuda_without_one_is_an_error_not_a_cpu_run():
    with pytest.raises(ValueError, match="device: 'cuda' asked for, but this machine has no CUDA"):
        resolve_device("cuda")


def test_an_unknown_device_is_named():
    with pytest.raises(ValueError, match="'mps' is not auto, cpu or cuda"):
        resolve_device("mps")
