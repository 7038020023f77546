"""What every part of the scene schema shares: strict validation (unknown keys,
strings for numbers, values float32 cannot hold are errors) and the vector types."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, Strict, field_validator, model_validator

# Types are strict (a string is not a number, 1 is not true) except that an integer is
# a valid float (TOML ``dx = 1``) and containers are lax: a vector may be a TOML list or
# a Python list or tuple, a path a string. The items of a container stay strict.
PositiveFloat = Annotated[float, Field(gt=0)]
Vec3 = Annotated[tuple[float, float, float], Strict(False)]
Pair = Annotated[tuple[PositiveFloat, PositiveFloat], Strict(False)]
Triple = Annotated[tuple[PositiveFloat, PositiveFloat, PositiveFloat], Strict(False)]
FilePath = Annotated[Path, Strict(False)]
Box = Annotated[tuple[Vec3, Vec3], Strict(False)]

# The solver computes in single precision: a number beyond FLOAT32_MAX cannot even be
# stored, and a non-zero one below FLOAT32_TINY loses its precision or becomes 0.
FLOAT32_MAX = 3.4028234663852886e38
FLOAT32_TINY = 1.1754943508222875e-38


def _plain(value):
    """numpy scalars and arrays (np.float32, np.int64, np.bool_) -> Python numbers and
    lists, recursively, so that strict validation treats them like the Python values."""
    if isinstance(value, (list, tuple)):
        out = [_plain(v) for v in value]
        return tuple(out) if isinstance(value, tuple) else out
    if type(value).__module__ == "numpy" and hasattr(value, "tolist"):
        return value.tolist()
    return value


def _out_of_range(value, index: tuple = ()):
    """(index, value) of the first float in ``value`` that float32 cannot hold, or None."""
    if isinstance(value, float) and (abs(value) > FLOAT32_MAX or 0.0 < abs(value) < FLOAT32_TINY):
        return index, value
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            found = _out_of_range(v, index + (i,))
            if found is not None:
                return found
    return None


class _Strict(BaseModel):
    # Unknown keys are errors: a typo in a scene file must not be silently ignored.
    # strict: "0.04" is not a number and "yes" is not a boolean; allow_inf_nan: inf and
    # nan (valid TOML) are refused wherever a number is expected, vectors included.
    model_config = ConfigDict(extra="forbid", validate_assignment=True, strict=True, allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _numpy_scalars(cls, data):
        return {k: _plain(v) for k, v in data.items()} if isinstance(data, dict) else data

    @field_validator("*", mode="after")
    @classmethod
    def _single_precision(cls, value):
        found = _out_of_range(value)
        if found is not None:
            index, x = found
            item = f" (item {''.join(f'[{i}]' for i in index)})" if index else ""
            raise ValueError(
                f"{x:g}{item} is outside the single-precision range of the solver "
                "(0 or 1.2e-38 <= |x| <= 3.4e38)"
            )
        return value


@classmethod
def positive_scale(cls, s):
    """A field validator for ``scale``: a single number must be > 0 (a triple's items
    are positive by type)."""
    if isinstance(s, (int, float)) and s <= 0:
        raise ValueError("must be > 0")
    return s
