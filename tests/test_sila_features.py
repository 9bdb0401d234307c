"""The SiLA server's parts that need no daemon: its feature definitions, as the reference
``sila2`` package's own tools read them, the implementations against them, the mapping of
the cell's typed errors, and the server's stored identity (UUID, certificate, key)."""

from __future__ import annotations

import py_compile
import stat
from pathlib import Path

import pytest
from cryptography import x509
from sila2.code_generator.feature_generator import FeatureGenerator
from sila2.framework import Feature

from fxcell import errors
from fxcell.config import CellConfig
from fxcell.daemon.sila import identity
from fxcell.daemon.sila.bridge import CELL_ERRORS, FEATURES, ErrorMap, load_feature
from fxcell.daemon.sila.cell import (
    TRANSFER_ERRORS,
    CellController,
    LabwareTransferManipulatorController,
    SimulationController,
)
from fxcell.daemon.sila.job import JOB_ERRORS, ErrorRecoveryService, JobController
from fxcell.daemon.sila.server import FEATURE_FILES
from fxcell.info import sila_line

IMPLEMENTATIONS = {
    "CellController": CellController,
    "JobController": JobController,
    "ErrorRecoveryService": ErrorRecoveryService,
    "SimulationController": SimulationController,
    "LabwareTransferManipulatorController": LabwareTransferManipulatorController,
}
FILES = sorted(FEATURES.glob("*.sila.xml"))


def test_every_feature_definition_in_the_package_is_served() -> None:
    assert {f.name.removesuffix(".sila.xml") for f in FILES} == set(FEATURE_FILES)
    assert set(IMPLEMENTATIONS) == set(FEATURE_FILES)


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_feature_definition_is_valid_for_the_reference_tools(path: Path, tmp_path: Path) -> None:
    # Feature() validates against the standard's FeatureDefinition.xsd and compiles the protobuf
    feature = Feature(str(path))
    assert feature._identifier == path.name.removesuffix(".sila.xml")
    # sila2-codegen (its generate-feature-files) turns it into base classes and client stubs
    generator = FeatureGenerator(feature, overwrite=True)
    out = tmp_path / feature._identifier.lower()
    generator.generate_feature_files(out_dir=str(out), part_of_server_package=False)
    generated = sorted(out.glob("*.py"))
    assert any(p.name.endswith("_base.py") for p in generated), generated
    for file in generated:
        py_compile.compile(str(file), doraise=True)


@pytest.mark.parametrize("name", FEATURE_FILES)
def test_implementation_answers_every_call_of_its_definition(name: str) -> None:
    feature = load_feature(name)
    impl = IMPLEMENTATIONS[name]
    wanted = [
        *feature._unobservable_commands,
        *feature._observable_commands,
        *(f"get_{p}" for p in feature._unobservable_properties),
        *(f"{p}_on_subscription" for p in feature._observable_properties),
    ]
    missing = [w for w in wanted if not callable(getattr(impl, w, None))]
    assert not missing, missing


def test_cell_errors_keep_their_typed_name_and_next_step() -> None:
    cell = ErrorMap(load_feature("CellController"), CELL_ERRORS, "CellError")
    refused = errors.InvalidStateError("move_joint", "idle", ["running"], "run init first")
    error = cell.translate(refused)
    assert error.identifier == "InvalidState"
    assert error.message.startswith("InvalidStateError: ")
    assert "run init first" in error.message
    assert cell.identifier(errors.UnknownPositionError("no such position")) == "InvalidArgument"
    assert cell.identifier(errors.ProtectiveStopError("stopped")) == "SafetyStop"
    assert cell.identifier(errors.NothingGraspedError("empty")) == "GripperFailed"
    assert cell.identifier(errors.MoveStoppedError("stopped")) == "MoveFailed"
    assert cell.identifier(errors.ControlHeldError("held", status=409)) == "ControlHeld"
    assert cell.identifier(errors.RecorderError("disk full")) == "CellError"
    transfer = ErrorMap(
        load_feature("LabwareTransferManipulatorController"),
        TRANSFER_ERRORS,
        "LabwareTransferFailed",
    )
    assert transfer.identifier(errors.SlotError("no slot Z9")) == "HandoverPositionUnknown"
    assert transfer.identifier(errors.HoldingError("holds one")) == "LabwareTransferFailed"
    job = ErrorMap(load_feature("JobController"), JOB_ERRORS, "JobRefused")
    assert job.identifier(errors.JobSpecError("bad", sample="S1", field="rack")) == "InvalidRun"
    assert job.identifier(errors.JobStateError("abort", "idle", ["running"])) == "JobRefused"


def test_error_map_refuses_an_error_its_feature_does_not_define() -> None:
    with pytest.raises(ValueError, match="defines no error"):
        ErrorMap(load_feature("JobController"), {errors.MoveError: "MoveFailed"}, "JobRefused")


def _config(tmp_path: Path, host: str = "127.0.0.1") -> CellConfig:
    return CellConfig.from_dict(
        {"daemon": {"host": host, "token_file": str(tmp_path / "state" / "token")}},
        source="test",
    )


def test_identity_is_made_once_owner_only_and_kept(tmp_path: Path) -> None:
    config = _config(tmp_path)
    first = identity.load_or_create(config)
    directory = tmp_path / "state"
    for name in (identity.UUID_FILE, identity.CERT_FILE, identity.KEY_FILE):
        assert stat.S_IMODE((directory / name).stat().st_mode) == 0o600, name
    assert stat.S_IMODE(directory.stat().st_mode) == 0o700
    again = identity.load_or_create(config)
    assert again == first
    cert = x509.load_pem_x509_certificate(first.certificate)
    carried = cert.extensions.get_extension_for_oid(x509.ObjectIdentifier(identity.SILA_UUID_OID))
    assert carried.value.value == str(first.server_uuid).encode()  # type: ignore[attr-defined]
    common = cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)
    assert [a.value for a in common] == ["SiLA2"]
    assert len(first.fingerprint.split(":")) == 32
    assert first.fingerprint in sila_line(config)


def test_certificate_follows_the_address_and_keeps_the_uuid(tmp_path: Path) -> None:
    first = identity.load_or_create(_config(tmp_path, "127.0.0.1"))
    moved = identity.load_or_create(_config(tmp_path, "127.0.0.7"))
    assert moved.server_uuid == first.server_uuid
    assert moved.certificate != first.certificate
    san = x509.load_pem_x509_certificate(moved.certificate).extensions.get_extension_for_class(
        x509.SubjectAlternativeName
    )
    assert "127.0.0.7" in {str(ip) for ip in san.value.get_values_for_type(x509.IPAddress)}


def test_identity_readable_by_others_is_refused(tmp_path: Path) -> None:
    config = _config(tmp_path)
    identity.load_or_create(config)
    key = tmp_path / "state" / identity.KEY_FILE
    key.chmod(0o644)
    with pytest.raises(errors.ConfigError, match="chmod 600"):
        identity.load_or_create(config)


def test_corrupt_uuid_file_is_refused_with_the_fix(tmp_path: Path) -> None:
    config = _config(tmp_path)
    (tmp_path / "state").mkdir(mode=0o700)
    (tmp_path / "state" / identity.UUID_FILE).write_text("not a uuid\n")
    with pytest.raises(errors.ConfigError, match="delete it"):
        identity.load_or_create(config)


def test_info_says_where_the_certificate_will_be_before_the_first_start(tmp_path: Path) -> None:
    line = sila_line(_config(tmp_path))
    assert "no certificate yet" in line
    assert str(tmp_path / "state" / identity.CERT_FILE) in line
