"""Observations as named arrays: the spec an environment declares, its wire form, and the check
each daemon makes of observation data at its edge (docs/observations.md).

An observation maps field names to arrays of a declared dtype and shape, in a declared order:
``{"state": float32[41]}`` for the runner, ``{"pixels": uint8[3, 84, 84]}`` for a camera task.
A gymnasium ``Box`` is one field named ``"state"`` (gymnasium's own name for the vector beside
``"pixels"``), so every task l2r ran before is this one-field case; a ``Dict`` of ``Box`` spaces
is one field per key, in the Dict's order. Floating-point Boxes become float32 (gymnasium's
MuJoCo tasks declare float64; the wire and the networks use float32). uint8 stays uint8 all the
way to the device that trains, which scales it: a frame costs a quarter of its float32 bytes in
every buffer and message on the way.

On the wire a spec is a list of ``{"name": "pixels", "dtype": "uint8", "shape": [3, 84, 84]}``
maps, in field order.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from types import MappingProxyType
from typing import Any

import numpy as np

from l2r.protocol.errors import ProtocolError

VECTOR_FIELD = "state"
"""The field of a Box observation: the float32 vector every l2r task had before named fields."""
DTYPES = {d.name: d for d in map(np.dtype, ("uint8", "float32"))}
"""The dtypes a field may have, by name: frames and vectors."""
MAX_FIELDS = 8
MAX_FIELD_DIMS = 3
"""Channels, height, width; on the wire rows come first, within the 4 dimensions an array may have."""
MAX_FIELD_BYTES = 4 * 2**20
"""Bytes of one field of one observation: a 1024 x 1024 RGB photo is 3 MiB."""
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,31}")
_TEXT_FIELD = re.compile(r"\s*([^:,\s]+)\s*:\s*(\w+)\s*\[([^\]]*)\]\s*")
"""One field of the text form: ``pixels: uint8[3, 84, 84]``."""


@dataclass(frozen=True)
class FieldSpec:
    """One named array of an observation."""

    dtype: np.dtype
    shape: tuple[int, ...]

    def __post_init__(self) -> None:  # accept np.uint8 for np.dtype("uint8"), a list for a tuple
        object.__setattr__(self, "dtype", np.dtype(self.dtype))
        object.__setattr__(self, "shape", tuple(self.shape))

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize

    def __str__(self) -> str:
        return f"{self.dtype.name}[{', '.join(map(str, self.shape))}]"


class ObservationSpec:
    """Field name -> `FieldSpec`, in order, read-only. Building one checks every field and raises
    ProtocolError with the reason: ``bad_field`` (a name that is not ``[A-Za-z_][A-Za-z0-9_]*``
    of at most 32 characters, no fields, more than 8), ``wrong_dtype`` (not uint8 or float32),
    ``wrong_shape`` (not 1 to 3 dimensions of at least 1) or ``oversized`` (over 4 MiB)."""

    def __init__(self, fields: Mapping[str, FieldSpec], where: str = "observation"):
        if not 0 < len(fields) <= MAX_FIELDS:
            raise ProtocolError(f"{where}: {len(fields)} fields, expected 1 to {MAX_FIELDS}", "bad_field")
        for name, spec in fields.items():
            if not isinstance(name, str) or not _NAME.fullmatch(name):
                raise ProtocolError(f"{where}: field name {name!r:.40} is not [A-Za-z_][A-Za-z0-9_]* of at most 32 "
                                    "characters", "bad_field")
            if spec.dtype not in DTYPES.values():
                raise ProtocolError(f"{where}.{name}: dtype {spec.dtype}, expected one of {', '.join(DTYPES)}",
                                    "wrong_dtype")
            if (not 1 <= len(spec.shape) <= MAX_FIELD_DIMS
                    or not all(type(d) is int and d >= 1 for d in spec.shape)):
                raise ProtocolError(f"{where}.{name}: shape {list(spec.shape)}, expected 1 to {MAX_FIELD_DIMS} "
                                    "dimensions of at least 1", "wrong_shape")
            if spec.nbytes > MAX_FIELD_BYTES:
                raise ProtocolError(f"{where}.{name}: {spec} takes {spec.nbytes} bytes, more than "
                                    f"{MAX_FIELD_BYTES}", "oversized")
        self.fields = MappingProxyType(dict(fields))

    def __eq__(self, other: object) -> bool:
        return self is other or (isinstance(other, ObservationSpec)
                                 and list(self.fields.items()) == list(other.fields.items()))

    def __str__(self) -> str:
        return "{" + ", ".join(f"{name}: {spec}" for name, spec in self.fields.items()) + "}"

    def __repr__(self) -> str:
        return f"ObservationSpec({self})"

    def __deepcopy__(self, memo: dict) -> ObservationSpec:
        return self  # read-only: a copy of a network (a target network) shares its spec

    @classmethod
    def parse(cls, text: str) -> ObservationSpec:
        """The spec written as ``str(spec)`` prints it, braces optional: ``pixels: uint8[3, 84, 84],
        state: float32[24]``. ProtocolError (``bad_spec`` for text of another form, else the
        reason of the bad field) with a message that quotes what could not be read."""
        body = text.strip()
        if body.startswith("{") and body.endswith("}"):
            body = body[1:-1]
        fields, at = {}, 0
        while at < len(body) or not fields:
            match = _TEXT_FIELD.match(body, at)
            if match is None:
                raise ProtocolError(f"observation {text!r:.80}: cannot read {body[at:]!r:.40}; expected fields as "
                                    "'name: dtype[d1, d2, ...]' separated by commas", "bad_spec")
            name, dtype, dims = match.groups()
            if name in fields:
                raise ProtocolError(f"observation {text!r:.80}: field {name!r} comes twice", "bad_field")
            if dtype not in DTYPES:
                raise ProtocolError(f"observation.{name}: dtype {dtype!r:.20}, expected one of {', '.join(DTYPES)}",
                                    "wrong_dtype")
            try:
                shape = tuple(int(d) for d in dims.split(","))
            except ValueError:
                raise ProtocolError(f"observation.{name}: shape [{dims:.40}] is not whole numbers separated by "
                                    "commas", "wrong_shape") from None
            fields[name] = FieldSpec(DTYPES[dtype], shape)
            at = match.end()
            if at < len(body):
                if body[at] != ",":
                    raise ProtocolError(f"observation {text!r:.80}: expected a comma before {body[at:]!r:.40}",
                                        "bad_spec")
                at += 1
        return cls(fields)

    @classmethod
    def vector(cls, width: int) -> ObservationSpec:
        """The float32 vector of ``width`` values, the field "state"."""
        return cls({VECTOR_FIELD: FieldSpec(DTYPES["float32"], (width,))})

    @property
    def vector_width(self) -> int | None:
        """The width when this is the float32 vector ("state" alone), else None."""
        spec = self.fields.get(VECTOR_FIELD)
        if len(self.fields) == 1 and spec is not None and spec.dtype == DTYPES["float32"] and len(spec.shape) == 1:
            return spec.shape[0]
        return None

    @classmethod
    def from_space(cls, space: Any) -> ObservationSpec:
        """The spec of a gymnasium observation space: a Box, or a Dict of Box spaces; raise
        ValueError for any other."""
        from gymnasium import spaces

        items = space.spaces.items() if isinstance(space, spaces.Dict) else [(VECTOR_FIELD, space)]
        fields = {}
        for name, box in items:
            if not isinstance(box, spaces.Box):
                raise ValueError(f"observation {name!r} is a {type(box).__name__} space; l2r takes a Box or a "
                                 "Dict of Box spaces")
            if np.issubdtype(box.dtype, np.floating):
                dtype = DTYPES["float32"]
            elif box.dtype == DTYPES["uint8"]:
                dtype = box.dtype
            else:
                raise ValueError(f"observation {name!r} has dtype {box.dtype}; l2r takes uint8 or floating-point "
                                 "Box spaces")
            fields[name] = FieldSpec(dtype, tuple(int(d) for d in box.shape))
        return cls(fields, "observation space")

    def to_wire(self) -> list[dict]:
        """The msgpack-native form: a list of {"name", "dtype", "shape"} maps in field order."""
        return [{"name": name, "dtype": spec.dtype.name, "shape": list(spec.shape)}
                for name, spec in self.fields.items()]

    @classmethod
    def from_wire(cls, raw: Any, where: str = "observation spec") -> ObservationSpec:
        """Parse `to_wire`'s form, as a peer sent it; raise ProtocolError (``bad_spec`` when it is
        not a list of such maps, or one of the reasons of a bad field)."""
        if not isinstance(raw, list):
            raise ProtocolError(f"{where}: expected a list of fields, got {type(raw).__name__}", "bad_spec")
        if len(raw) > MAX_FIELDS:
            raise ProtocolError(f"{where}: {len(raw)} fields, expected 1 to {MAX_FIELDS}", "bad_field")
        fields = {}
        for entry in raw:
            if not isinstance(entry, dict) or set(entry) != {"name", "dtype", "shape"}:
                raise ProtocolError(f"{where}: expected fields as maps of name, dtype and shape, got {entry!r:.80}",
                                    "bad_spec")
            name, dtype, shape = entry["name"], entry["dtype"], entry["shape"]
            if not isinstance(name, str) or name in fields:
                raise ProtocolError(f"{where}: field name {name!r:.40} is not a string, or comes twice", "bad_field")
            if not isinstance(dtype, str) or dtype not in DTYPES:  # a name: "uint8", never "|u1" or "B"
                raise ProtocolError(f"{where}.{name}: dtype {dtype!r:.40}, expected one of {', '.join(DTYPES)}",
                                    "wrong_dtype")
            if not isinstance(shape, list):
                raise ProtocolError(f"{where}.{name}: shape {shape!r:.40} is not a list", "wrong_shape")
            fields[name] = FieldSpec(DTYPES[dtype], tuple(shape))
        return cls(fields, where)

    @classmethod
    def of_rows(cls, fields: Mapping[str, np.ndarray], where: str) -> ObservationSpec:
        """The spec that rows of observations follow: each array's dtype and its shape past the
        first dimension, the rows (ProtocolError if that is no spec)."""
        for name, rows in fields.items():
            if not isinstance(rows, np.ndarray) or rows.ndim < 1:
                raise ProtocolError(f"{where}.{name}: expected an array with rows first, got "
                                    f"{getattr(rows, 'shape', type(rows).__name__)}", "wrong_shape")
        return _spec_of(tuple((name, rows.dtype, rows.shape[1:]) for name, rows in fields.items()), where)

    def check(self, fields: Mapping[str, np.ndarray], where: str, rows: bool = True) -> None:
        """Raise ProtocolError unless ``fields`` are this spec's fields, each of its field's dtype
        and shape, after a first dimension of rows when ``rows``. The check at a daemon's edge."""
        unknown = [name for name in fields if name not in self.fields]
        if unknown:
            raise ProtocolError(f"{where}: fields {unknown} are not in the observation {self}", "unknown_field")
        missing = [name for name in self.fields if name not in fields]
        if missing:
            raise ProtocolError(f"{where}: fields {missing} of the observation {self} are missing", "missing_field")
        for name, spec in self.fields.items():
            array = fields[name]
            if array.dtype != spec.dtype:
                raise ProtocolError(f"{where}.{name}: dtype {array.dtype}, expected {spec.dtype}", "wrong_dtype")
            if array.shape[int(rows):] != spec.shape:
                expected = list(spec.shape) if not rows else f"[rows, {', '.join(map(str, spec.shape))}]"
                raise ProtocolError(f"{where}.{name}: shape {list(array.shape)}, expected {expected}", "wrong_shape")

    def fields_of(self, observation: Any) -> dict[str, np.ndarray]:
        """One observation as an environment returns it, as this spec's fields: a Box's array is
        the field "state", a Dict's entries are their fields, floating-point values of float32
        fields become float32. ProtocolError when it does not fit the spec."""
        if isinstance(observation, np.ndarray) and len(self.fields) == 1:  # a vector as the spec has it: as it is
            spec = self.fields.get(VECTOR_FIELD)
            if spec is not None and observation.dtype == spec.dtype and observation.shape == spec.shape:
                return {VECTOR_FIELD: observation}
        values = observation if isinstance(observation, Mapping) else {VECTOR_FIELD: observation}
        fields = {}
        for name, value in values.items():
            array = np.asarray(value)
            if array.dtype.kind == "f" and name in self.fields and self.fields[name].dtype == DTYPES["float32"]:
                array = array.astype(np.float32, copy=False)
            fields[name] = array
        self.check(fields, "observation", rows=False)
        return fields

    @classmethod
    def from_policy_spec(cls, spec: Mapping) -> ObservationSpec:
        """The observation a policy spec (of weights or a checkpoint) was built for: its
        "observation" entry, or in specs from before it, the float32 vector of "obs_dim"."""
        if "observation" in spec:
            return cls.from_wire(spec["observation"], "policy spec observation")
        width = spec.get("obs_dim")
        if type(width) is not int:
            raise ProtocolError(f"policy spec has no observation and an obs_dim of {width!r:.40}", "bad_spec")
        return cls.vector(width)

    def policy_entries(self) -> dict:
        """What a policy spec carries of this observation: "observation", and "obs_dim" while it
        is the float32 vector, for actors that know only that."""
        entries: dict = {"observation": self.to_wire()}
        if self.vector_width is not None:
            entries["obs_dim"] = self.vector_width
        return entries


@lru_cache(maxsize=64)
def _spec_of(fields: tuple[tuple[str, np.dtype, tuple[int, ...]], ...], where: str) -> ObservationSpec:
    """(Cached: a daemon meets the same few specs in every message; a bad one raises, and is not kept.)"""
    return ObservationSpec({name: FieldSpec(dtype, shape) for name, dtype, shape in fields}, where)


def as_fields(rows: np.ndarray | Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rows of observations as a message holds them, as fields: a plain matrix is the vector
    observation (the field "state", float32); a map already is fields."""
    if isinstance(rows, np.ndarray):
        return {VECTOR_FIELD: np.asarray(rows, np.float32)}
    if isinstance(rows, Mapping):
        return dict(rows)
    raise ProtocolError(f"observations must be an array or a map of fields, got {type(rows).__name__}", "wrong_type")
