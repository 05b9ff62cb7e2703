"""The protocol's retry rule and backoff, and what counts as a gateway URL."""

from __future__ import annotations

import pytest

from agent.gateway import Backoff, check_url, retryable


def test_backoff_doubles_from_a_fifth_of_a_second_to_five_seconds() -> None:
    backoff = Backoff()
    assert [backoff.next() for _ in range(7)] == [0.2, 0.4, 0.8, 1.6, 3.2, 5.0, 5.0]
    backoff.reset()
    assert backoff.next() == 0.2


def test_only_server_errors_timeouts_and_too_many_requests_are_retried() -> None:
    assert all(retryable(s) for s in (500, 502, 503, 504, 408, 429))
    assert not any(retryable(s) for s in (400, 401, 404, 409, 413, 415, 422))


@pytest.mark.parametrize("url", ["localhost:8000", "ftp://host", "http://", "", "not a url"])
def test_a_gateway_url_is_http_or_https_with_a_host(url: str) -> None:
    with pytest.raises(ValueError, match="--gateway"):
        check_url(url)


def test_a_trailing_slash_does_not_make_another_gateway() -> None:
    assert check_url("https://rig.example:8443/") == check_url("https://rig.example:8443")
