"""Property-based fuzzing of the live service from its own /openapi.json (schemathesis + hypothesis).

Every generated request, valid or deliberately invalid, must get an answer that is not a 5xx and
that conforms to the documented statuses and schemas. And the schema must say what /register accepts:
a request valid by the schema may be refused only for what JSON Schema cannot express (a cloud whose
points do not span 3-D), and most of them must be registered. ``scripts/fuzz.py`` runs the same test
with more cases (``PRANET_FUZZ_EXAMPLES``) or against another server (``PRANET_FUZZ_URL``).
"""

from __future__ import annotations

import os
import re
from collections import Counter
from typing import Any

import numpy as np
import pytest

from pranet.core.wire import ENCODING, encode_cloud
from pranet.service.schemas import MAX_ABS_COORDINATE, MIN_POINTS

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, Phase, given, settings  # noqa: E402 - after the importorskip
from hypothesis import strategies as st  # noqa: E402
from schemathesis import GenerationMode  # noqa: E402
from schemathesis.checks import not_a_server_error  # noqa: E402
from schemathesis.specs.openapi.checks import (  # noqa: E402
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

pytestmark = pytest.mark.slow

EXAMPLES = int(os.environ.get("PRANET_FUZZ_EXAMPLES", "1000"))  # /register cases; 60 % valid by the schema
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]
FUZZ_SETTINGS = settings(
    deadline=None,
    database=None,
    derandomize=os.environ.get("PRANET_FUZZ_RANDOM") != "1",  # a fixed seed (cases may still vary a little)
    phases=[Phase.explicit, Phase.generate],
    suppress_health_check=list(HealthCheck),
)
# What JSON Schema cannot say about a cloud, so a request valid by the schema may still be refused for it.
GEOMETRY = re.compile(r"^(source|target): (all points are identical|points are collinear)")
MIN_REGISTERED = 0.5  # of the requests valid by the schema (measured: docs/DESIGN.md, "The edge")


def _encoded_clouds() -> st.SearchStrategy[str]:
    """The schema's ``format: base64-float32-le``: what its pattern cannot say (the float32 values are finite and
    within the coordinate bounds), as a generator that knows the encoding (any client's encoder) writes it."""
    coordinate = st.floats(-MAX_ABS_COORDINATE, MAX_ABS_COORDINATE, width=32, allow_nan=False, allow_infinity=False)
    points = st.integers(MIN_POINTS, 64).flatmap(lambda n: st.lists(coordinate, min_size=3 * n, max_size=3 * n))
    return points.map(lambda values: encode_cloud(np.asarray(values, dtype=np.float32))["data"])


schemathesis.openapi.format(ENCODING, _encoded_clouds())


@pytest.fixture(scope="module")
def api_schema(request: pytest.FixtureRequest) -> Any:
    url = os.environ.get("PRANET_FUZZ_URL") or request.getfixturevalue("server_url")
    key = os.environ.get("PRANET_FUZZ_API_KEY")
    headers = {"Authorization": f"Bearer {key}"} if key else {}
    return schemathesis.openapi.from_url(f"{url}/openapi.json", headers=headers), url, headers


def _fewer_steps(case: Any) -> None:
    """Bound the agent work of a valid body (the schema allows 2 x 200 steps, x 120 starts in global mode)."""
    body = case.body
    if isinstance(body, dict) and "source" in body and "target" in body:
        steps = body.get("steps")
        body["steps"] = [min(s, 2) for s in steps] if isinstance(steps, list) and steps else [1, 1]
        if isinstance(body.get("starts"), int):
            body["starts"] = min(body["starts"], 4)  # init='global' multiplies the agent's work by the starts


def _fuzz(
    schema: Any, url: str, headers: dict, path: str, method: str, mode: GenerationMode, n: int
) -> tuple[Counter, Counter]:
    """Run ``n`` generated cases -> (their statuses, the refusals' messages)."""
    import requests

    statuses: Counter = Counter()
    refusals: Counter = Counter()
    operation = schema[path][method]

    with requests.Session() as session:

        @settings(FUZZ_SETTINGS, max_examples=n)
        @given(case=operation.as_strategy(generation_mode=mode))
        def run(case: Any) -> None:
            if mode is GenerationMode.POSITIVE:
                _fewer_steps(case)  # a negative case must stay invalid: leave it as generated
            response = case.call(base_url=url, session=session, headers=headers, timeout=120)
            checks = CHECKS if mode is GenerationMode.POSITIVE else [not_a_server_error]
            case.validate_response(response, checks=checks, headers=headers)
            statuses[response.status_code] += 1
            if 400 <= response.status_code < 500:
                refusals[_message(response.json()["detail"])] += 1

        run()
    return statuses, refusals


def _message(detail: str | list[dict]) -> str:
    if isinstance(detail, str):
        return detail
    return "; ".join(f"{'.'.join(map(str, e.get('loc', ())))}: {e.get('msg')}" for e in detail)


def test_fuzz_register(api_schema: Any) -> None:
    schema, url, headers = api_schema
    valid, refused = _fuzz(schema, url, headers, "/register", "POST", GenerationMode.POSITIVE, int(EXAMPLES * 0.6))
    invalid, _ = _fuzz(schema, url, headers, "/register", "POST", GenerationMode.NEGATIVE, int(EXAMPLES * 0.4))
    print(f"\n/register statuses: valid-by-schema {dict(valid)}, invalid-by-schema {dict(invalid)}")
    print("valid-by-schema refused for:", dict(refused.most_common(10)))
    assert sum(valid.values()) + sum(invalid.values()) >= EXAMPLES * 0.95  # hypothesis may drop a few duplicates
    assert all(400 <= status < 500 for status in invalid), invalid
    # The schema says what /register accepts: nothing valid by it is refused for a reason the schema could state.
    unstated = {message: n for message, n in refused.items() if not GEOMETRY.match(message)}
    assert not unstated, f"requests valid by the schema refused for what it does not say: {unstated}"
    share = valid[200] / sum(valid.values())
    assert share >= MIN_REGISTERED, f"only {share:.0%} of the requests valid by the schema were registered: {valid}"


@pytest.mark.parametrize(("path", "method"), [("/health", "GET"), ("/ready", "GET"), ("/model", "GET")])
def test_fuzz_read_routes(api_schema: Any, path: str, method: str) -> None:
    schema, url, headers = api_schema
    statuses, _ = _fuzz(schema, url, headers, path, method, GenerationMode.POSITIVE, 20)
    assert set(statuses) == {200}
