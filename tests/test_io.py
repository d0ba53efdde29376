"""Results files are strict JSON: a non-finite number is written as ``null``."""

import json
import math

from dronefl.io import atomic_write_json


def test_non_finite_numbers_are_written_as_null(tmp_path):
    path = atomic_write_json(
        tmp_path / "r.json", {"mse": math.nan, "ratio": [1.5, math.inf, -math.inf], "n": 3}
    )

    def strict(token: str) -> float:
        raise ValueError(f"not JSON: {token}")

    assert json.loads(path.read_text(), parse_constant=strict) == {
        "mse": None, "ratio": [1.5, None, None], "n": 3
    }  # fmt: skip
