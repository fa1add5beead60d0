"""The Python client (and so the CLI) sends a request again when the server answers 503 or 429
with Retry-After (docs/api.md: nothing was done), after the delay asked for, within a bounded
number of sends and seconds; other answers, and a 503 without Retry-After, are final."""

from __future__ import annotations

import httpx
import pytest

from renderfarm.client import ApiError, Client, RetryAfterTransport


class Answers:
    """A server that answers from a list, recording what it was sent."""

    def __init__(self, answers: list[tuple[int, dict[str, str]]]):
        self.answers = list(answers)
        self.requests: list[tuple[str, bytes]] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append((request.method, request.read()))
        status, headers = self.answers.pop(0) if len(self.answers) > 1 else self.answers[0]
        body = {"id": "abc"} if status < 400 else {"detail": "busy", "field": "database"}
        return httpx.Response(status, json=body, headers=headers)


def client_with(answers: Answers, slept: list[float], **limits) -> Client:
    client = Client("http://farm.invalid")
    transport = RetryAfterTransport(httpx.MockTransport(answers), sleep=slept.append, **limits)
    client.http = httpx.Client(base_url=client.url, transport=transport)
    return client


def test_a_503_with_retry_after_is_sent_again_after_that_delay():
    answers = Answers([(503, {"Retry-After": "2"}), (429, {"Retry-After": "1"}), (200, {})])
    slept: list[float] = []
    with client_with(answers, slept) as client:
        assert client.get("abc") == {"id": "abc"}
    assert slept == [2.0, 1.0]
    assert [m for m, _ in answers.requests] == ["GET"] * 3


def test_an_upload_is_sent_again_whole(tmp_path):
    scene = tmp_path / "scene.glb"
    scene.write_bytes(b"glTF" + bytes(range(256)) * 64)
    answers = Answers([(503, {"Retry-After": "1"}), (201, {})])
    slept: list[float] = []
    with client_with(answers, slept) as client:
        client.submit(scene, settings={"max_spp": 4}, name="again")
    (first, body1), (second, body2) = answers.requests
    assert first == second == "POST" and body1 == body2
    assert scene.read_bytes() in body1 and b'{"max_spp": 4}' in body1


@pytest.mark.parametrize(
    "status, headers",
    [(503, {}), (500, {"Retry-After": "1"}), (404, {}), (503, {"Retry-After": "soon"})],
)
def test_answers_without_a_usable_retry_after_are_final(status, headers):
    answers = Answers([(status, headers), (200, {})])
    slept: list[float] = []
    with client_with(answers, slept) as client, pytest.raises(ApiError) as refused:
        client.get("abc")
    assert refused.value.status == status and slept == [] and len(answers.requests) == 1


def test_retries_are_bounded_by_attempts_and_by_time():
    answers = Answers([(503, {"Retry-After": "1"})])
    slept: list[float] = []
    with client_with(answers, slept, attempts=4) as client, pytest.raises(ApiError) as refused:
        client.get("abc")
    assert refused.value.status == 503 and len(answers.requests) == 4 and slept == [1.0] * 3

    answers = Answers([(503, {"Retry-After": "5"})])
    slept = []
    with client_with(answers, slept, budget_s=12) as client, pytest.raises(ApiError):
        client.get("abc")
    assert slept == [5.0, 5.0] and len(answers.requests) == 3  # a third wait would pass 12 s
