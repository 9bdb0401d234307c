"""A UR arm's factory calibration: per-joint DH deltas, UR's file and wire formats.

Every UR arm leaves the factory with corrections to its nominal Denavit-Hartenberg parameters,
stored on the controller in ``calibration.conf`` (section ``[mounting]``: ``delta_theta``,
``delta_a``, ``delta_d``, ``delta_alpha``, six values each, plus ``joint_checksum`` and
``calibration_status``). The controller computes ``actual_TCP_pose`` and its own moves with the
calibrated parameters (nominal + delta; the nominal θ are zero) and reports them in the
*kinematics info* sub-package (type 5) of the primary/secondary robot-state message:
checksum ``uint32[6]``, then ``double[6]`` each of θ, a, d, α, then ``uint32`` calibration status,
big-endian.

UR does not publish how it computes the per-joint checksums; fxcell's are the CRC-32 of the
joint's four calibrated values (big-endian doubles θ, a, d, α), so equal checksums mean equal
parameters. Pure standard library: the simulator and the robot link import this module.
"""

from __future__ import annotations

import math
import re
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from fxcell.errors import CalibrationError

Six = tuple[float, float, float, float, float, float]

UR3E_NOMINAL_D: Six = (0.15185, 0.0, 0.0, 0.13105, 0.08535, 0.0921)
UR3E_NOMINAL_A: Six = (0.0, -0.24355, -0.2132, 0.0, 0.0, 0.0)
UR3E_NOMINAL_ALPHA: Six = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
"""UR's published UR3e DH parameters (nominal θ are zero; the seed thesis's table has d5/d6
wrong): the one table, which :data:`fxcell.motion.kinematics.UR3E_DH` and the UR3e's
description for the views (:func:`fxcell.robots.ur3e.ur3e_description`) take."""


KINEMATICS_INFO_TYPE = 5
"""Sub-package type of the kinematics info in the primary/secondary robot-state message."""
_KIN_BODY = struct.Struct(">6I24dI")
KINEMATICS_INFO_SIZE = 5 + _KIN_BODY.size
"""Bytes of the whole sub-package, its 4-byte length and 1-byte type included (225)."""

CALIBRATION_STATUS_LINEARISED = 2
"""``calibration_status`` of a calibrated arm (0 not initialised, 1 not linearised,
2 linearised)."""

_ZERO: Six = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
_KEYS = ("delta_theta", "delta_a", "delta_d", "delta_alpha")


def _six(values: Sequence[float], what: str) -> Six:
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise CalibrationError(f"{what} must be 6 numbers, got {values!r}") from None
    if len(out) != 6 or not all(math.isfinite(v) for v in out):
        raise CalibrationError(f"{what} must be 6 finite numbers, got {values!r}")
    return out


@dataclass(frozen=True)
class Calibration:
    """Per-joint corrections to the nominal DH parameters (m, rad), UR's ``delta_*``."""

    delta_theta: Six = _ZERO
    delta_a: Six = _ZERO
    delta_d: Six = _ZERO
    delta_alpha: Six = _ZERO

    def __post_init__(self) -> None:
        for key in _KEYS:
            object.__setattr__(self, key, _six(getattr(self, key), key))

    @classmethod
    def nominal(cls) -> Calibration:
        """All-zero deltas: the arm as UR publishes it."""
        return cls()

    @property
    def is_nominal(self) -> bool:
        return all(v == 0.0 for key in _KEYS for v in getattr(self, key))

    @property
    def max_length_delta(self) -> float:
        """Largest |delta_a| or |delta_d| (m)."""
        return max(abs(v) for v in (*self.delta_a, *self.delta_d))

    @property
    def max_angle_delta(self) -> float:
        """Largest |delta_theta| or |delta_alpha| (rad)."""
        return max(abs(v) for v in (*self.delta_theta, *self.delta_alpha))

    # ------------------------------------------------------------ calibrated DH

    def dh(self) -> tuple[Six, Six, Six, Six]:
        """Calibrated UR3e DH parameters ``(theta, a, d, alpha)``: nominal + delta."""
        return (
            self.delta_theta,
            _add(UR3E_NOMINAL_A, self.delta_a),
            _add(UR3E_NOMINAL_D, self.delta_d),
            _add(UR3E_NOMINAL_ALPHA, self.delta_alpha),
        )

    @classmethod
    def from_dh(
        cls, theta: Sequence[float], a: Sequence[float], d: Sequence[float], alpha: Sequence[float]
    ) -> Calibration:
        """The deltas of calibrated UR3e DH parameters (as the kinematics info reports them)."""
        return cls(
            _six(theta, "DH theta"),
            _sub(_six(a, "DH a"), UR3E_NOMINAL_A),
            _sub(_six(d, "DH d"), UR3E_NOMINAL_D),
            _sub(_six(alpha, "DH alpha"), UR3E_NOMINAL_ALPHA),
        )

    def joint_checksums(self) -> tuple[int, ...]:
        """Per joint, the CRC-32 of its calibrated ``(θ, a, d, α)`` as big-endian doubles."""
        theta, a, d, alpha = self.dh()
        return tuple(
            zlib.crc32(struct.pack(">4d", theta[j], a[j], d[j], alpha[j])) for j in range(6)
        )

    @property
    def checksum(self) -> str:
        """One checksum of the whole calibration: CRC-32 over the joint checksums, 8 hex digits."""
        return f"{zlib.crc32(struct.pack('>6I', *self.joint_checksums())):08x}"

    def summary(self) -> dict[str, object]:
        """The deltas and checksums as plain data (MCAP metadata, JSON, the CLI)."""
        return {
            "delta_theta": list(self.delta_theta),
            "delta_a": list(self.delta_a),
            "delta_d": list(self.delta_d),
            "delta_alpha": list(self.delta_alpha),
            "joint_checksum": [f"0x{c:08x}" for c in self.joint_checksums()],
            "checksum": self.checksum,
            "nominal": self.is_nominal,
        }

    # ------------------------------------------------------------ calibration.conf

    @classmethod
    def parse_conf(cls, text: str, source: str = "calibration file") -> Calibration:
        """Read UR's ``calibration.conf`` text (``[mounting]`` section, ``key = [v, ...]``).

        Other keys (``joint_checksum``, ``calibration_status``, ``joint_raw_offset``, ...) are
        ignored; ``#`` starts a comment. CalibrationError when a delta is missing or malformed.
        """
        values: dict[str, str] = {}
        section = ""
        for raw in text.splitlines():
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            if line.startswith("[") and line.endswith("]"):
                section = line[1:-1].strip()
                continue
            key, sep, value = line.partition("=")
            if sep and section in ("", "mounting"):
                values[key.strip()] = value.strip()
        deltas: list[Six] = []
        for key in _KEYS:
            if key not in values:
                raise CalibrationError(f"{source}: no {key} in [mounting]")
            m = re.fullmatch(r"\[(.*)\]", values[key])
            if m is None:
                raise CalibrationError(f"{source}: {key} must be a [list], got {values[key]!r}")
            try:
                numbers = [float(v) for v in m.group(1).split(",") if v.strip()]
            except ValueError:
                raise CalibrationError(f"{source}: {key} is not numbers: {values[key]!r}") from None
            deltas.append(_six(numbers, f"{source}: {key}"))
        return cls(*deltas)

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read a ``calibration.conf`` file (CalibrationError if unreadable or malformed)."""
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as exc:
            raise CalibrationError(f"cannot read calibration file {path}: {exc}") from None
        return cls.parse_conf(text, str(path))

    def to_conf(self) -> str:
        """``calibration.conf`` text in UR's layout (readable back by :meth:`parse_conf`)."""

        def fmt(values: Sequence[float]) -> str:
            return "[ " + ", ".join(repr(float(v)) for v in values) + "]"

        sums = ", ".join(f"0x{c:x}" for c in self.joint_checksums())
        return (
            "[mounting]\n"
            + "".join(f"{key} = {fmt(getattr(self, key))}\n" for key in _KEYS)
            + f"joint_checksum = [ {sums}]\n"
            + f"calibration_status = {CALIBRATION_STATUS_LINEARISED}"
            " # 0 == notInitialized / 1 == notLinearised / 2 == Linearised\n"
        )

    # ------------------------------------------------------------ kinematics info

    def kinematics_info(self) -> bytes:
        """The kinematics info sub-package (length, type 5, body) of the robot-state message."""
        theta, a, d, alpha = self.dh()
        body = _KIN_BODY.pack(
            *self.joint_checksums(), *theta, *a, *d, *alpha, CALIBRATION_STATUS_LINEARISED
        )
        return struct.pack(">IB", KINEMATICS_INFO_SIZE, KINEMATICS_INFO_TYPE) + body

    @classmethod
    def from_kinematics_info(cls, package: bytes) -> Calibration:
        """Decode a kinematics info sub-package (with or without its 5-byte header).

        CalibrationError when it is malformed or a joint's checksum does not match its values.
        """
        if len(package) == KINEMATICS_INFO_SIZE:
            size, kind = struct.unpack_from(">IB", package)
            if size != KINEMATICS_INFO_SIZE or kind != KINEMATICS_INFO_TYPE:
                raise CalibrationError(f"not a kinematics info sub-package (type {kind})")
            package = package[5:]
        if len(package) != _KIN_BODY.size:
            raise CalibrationError(
                f"kinematics info must be {_KIN_BODY.size} bytes of body, got {len(package)}"
            )
        fields = _KIN_BODY.unpack(package)
        sums = fields[:6]
        theta, a, d, alpha = (fields[6 + 6 * k : 12 + 6 * k] for k in range(4))
        calibration = cls.from_dh(theta, a, d, alpha)
        # from_dh subtracts the nominal values: compare against checksums of what was sent
        expected = tuple(
            zlib.crc32(struct.pack(">4d", theta[j], a[j], d[j], alpha[j])) for j in range(6)
        )
        if tuple(sums) != expected:
            bad = [j + 1 for j in range(6) if sums[j] != expected[j]]
            raise CalibrationError(f"kinematics info: checksum mismatch on joint(s) {bad}")
        return calibration


def _add(a: Six, b: Six) -> Six:
    return tuple(x + y for x, y in zip(a, b, strict=True))  # type: ignore[return-value]


def _sub(a: Six, b: Six) -> Six:
    return tuple(x - y for x, y in zip(a, b, strict=True))  # type: ignore[return-value]
