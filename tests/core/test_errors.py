import ast
from pathlib import Path

import pytest

from core.errors import ErrorCode, FleetError, grpc_status, http_status
from services.rrd import errors as rrd_errors


def test_every_code_has_an_http_and_grpc_status():
    import grpc

    for code in ErrorCode:
        assert 400 <= http_status(code) < 600
        assert hasattr(grpc.StatusCode, grpc_status(code))


@pytest.mark.parametrize(
    ("exc", "status"),
    [
        (rrd_errors.NotAnRrdError("x", 0), 400),
        (rrd_errors.UnsupportedVersionError("x", 0), 400),
        (rrd_errors.TruncatedError("x", 5), 400),
        (rrd_errors.MessageTooLargeError("x", 12), 413),
    ],
)
def test_rrd_errors_are_fleet_errors_with_offsets(exc: rrd_errors.RrdError, status: int) -> None:
    assert isinstance(exc, FleetError)
    assert exc.http_status() == status
    assert f"at byte {exc.offset}" in str(exc)
    assert exc.to_dict()["code"] == exc.code.value


def test_no_bare_internal_error_is_raised_for_what_a_user_can_cause():
    """Every error raised in the service names its code: a bare FleetError maps to a 500."""
    root = Path(__file__).resolve().parents[2]
    bare = []
    for path in [*(root / "services").rglob("*.py"), *(root / "catalog").rglob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if (
                isinstance(node, ast.Raise)
                and isinstance(node.exc, ast.Call)
                and getattr(node.exc.func, "id", None) == "FleetError"
            ):
                bare.append(f"{path.relative_to(root)}:{node.lineno}")
    assert bare == []
