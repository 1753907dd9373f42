import pytest
import torch

from geofeat.errors import DeviceError
from geofeat.runtime.devices import resolve_device


def test_auto_cpu_and_bad_devices():
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto").type == expected and resolve_device(None).type == expected
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(DeviceError, match="device"):
        resolve_device("tpu:banana")
    if not torch.cuda.is_available():
        with pytest.raises(DeviceError, match="CUDA is not available"):
            resolve_device("cuda")
