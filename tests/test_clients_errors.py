"""The client error table is total over the service's codes, and bodies round-trip to the right typed class."""

from __future__ import annotations

import inspect

import pytest

from cadreg import errors as core
from clients import errors as cerr
from service import errors as wire


def _instance(cls: type) -> core.CadregError:
    params = inspect.signature(cls.__init__).parameters
    if "path" in params and "reason" in params:
        return cls("/tmp/x.ply", "broken")
    return cls("something went wrong")


def test_every_service_code_has_its_client_class() -> None:
    codes = {spec.code for spec in wire.ERROR_TABLE.values()} | {wire.INTERNAL.code}
    missing = sorted(codes - set(cerr.ERRORS_BY_CODE))
    assert not missing, f"no client error class for codes {missing}"
    for code in codes:
        client_cls = cerr.ERRORS_BY_CODE[code]
        assert client_cls.code == code
        # the client class is also the core/service class of that code, so `except core.X` catches it
        assert issubclass(client_cls, wire.CODE_TO_ERROR[code]), (code, client_cls, wire.CODE_TO_ERROR[code])
    assert set(cerr.ERRORS_BY_CODE) == codes, "client knows codes the service never sends"


@pytest.mark.parametrize("cls", list(wire.ERROR_TABLE), ids=lambda c: c.__name__)
def test_error_body_round_trips_to_the_typed_class(cls: type) -> None:
    exc = _instance(cls)
    spec = wire.spec_for(exc)
    body = wire.error_body(exc, request_id="req-1")
    got = cerr.error_from_body(body, status=spec.status)
    assert isinstance(got, cerr.ServerError)
    assert isinstance(got, cls)
    assert got.code == spec.code
    assert got.status == spec.status
    assert got.request_id == "req-1"
    assert got.message == exc.message
    assert got.retryable == spec.retry_after, "exactly the codes the service marks retryable are retried"
    if spec.retry_after:
        assert got.retry_after_s == pytest.approx(wire.retry_after_s(exc))


def test_invalid_file_keeps_its_path_and_overloaded_its_delay() -> None:
    body = wire.error_body(core.InvalidFileError("/data/site.json", "bad hash"))
    got = cerr.error_from_body(body, status=422)
    assert isinstance(got, cerr.InvalidFileError) and got.path == "/data/site.json"
    body = wire.error_body(core.Overloaded("queue full", retry_after_s=2.5))
    got = cerr.error_from_body(body, status=503)
    assert isinstance(got, core.Overloaded) and got.retry_after_s == 2.5
    # the service's own estimate in the body wins over the HTTP header, which rounds it up to whole seconds ...
    body = wire.error_body(core.Overloaded("queue full", retry_after_s=0.25))
    assert cerr.error_from_body(body, status=503, retry_after_s=1.0).retry_after_s == 0.25
    # ... and the header counts when the body has none (a proxy's 503, an older service)
    body["detail"].pop("retry_after_s")
    assert cerr.error_from_body(body, status=503, retry_after_s=4.0).retry_after_s == 4.0


def test_unknown_code_and_malformed_bodies() -> None:
    got = cerr.error_from_body({"code": "teapot", "message": "short and stout"}, status=418)
    assert type(got) is cerr.ServerError and got.code == "teapot" and not got.retryable
    for body in (None, [], "oops", {"message": "no code"}, {"code": 5}):
        got = cerr.error_from_body(body, status=500)
        assert isinstance(got, cerr.BadResponse) and got.code == "bad_response"


def test_client_only_errors() -> None:
    assert cerr.Unreachable("down").retryable
    t = cerr.ClientTimeout("slow")
    assert not t.retryable and isinstance(t, core.RequestTimeout) and t.code == "client_timeout"
    assert not cerr.BadResponse("html").retryable
    assert "HTTP 503" in str(cerr.Overloaded("busy", status=503, request_id="r9")) and "r9" in str(
        cerr.Overloaded("busy", status=503, request_id="r9"))
