"""Sizes in bytes: parsed from settings, formatted for messages."""

import numpy as np
import pytest

from geofeat.errors import GeofeatError, StoreError
from geofeat.storage.sizes import format_size, parse_size


@pytest.mark.parametrize(
    ("n_bytes", "text"),
    [(0, "0 bytes"), (999, "999 bytes"), (1000, "1.0 kB"), (1_048_576, "1.0 MB"), (6.4e9, "6.4 GB"), (1.5e12, "1.5 TB")],
)
def test_format_size_in_powers_of_1000(n_bytes, text):
    assert format_size(n_bytes) == text


def test_parse_size_in_powers_of_1024():
    assert parse_size("10G", "x") == 10 << 30 and parse_size(" 2 tib ", "x") == 2 << 40
    assert parse_size(np.int64(7), "x") == 7 and parse_size(0, "x") == 0 and parse_size("3", "x") == 3


@pytest.mark.parametrize("bad", [True, "", "G", "1 GG", "-5", -5, float("nan")])
def test_parse_size_names_the_setting_and_raises_the_given_error(bad):
    with pytest.raises(StoreError, match="^LIMIT must be a size"):
        parse_size(bad, "LIMIT", StoreError)
    with pytest.raises(GeofeatError, match="LIMIT"):
        parse_size(bad, "LIMIT")
