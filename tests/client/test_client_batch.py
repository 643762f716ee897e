"""register-many: the pairs file, the results file, retries over real HTTP, sharding, and a run killed with
SIGKILL and resumed (against a canned loopback service, and end to end on the real scans with pranet-serve)."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from client_helpers import canned_response, make_transform, run_console
from live_server import clean_env, console_script, free_port
from numpy.testing import assert_allclose

from pranet.client import PranetClient, RetryPolicy, read_pairs, write_point_cloud
from pranet.client.batch import (
    PairsFileError,
    ResultsFileError,
    read_results,
    reference_error,
    shard,
)
from pranet.client.client import PranetError
from pranet.core.se3 import rotation_angle

T_KNOWN = make_transform(20.0, (0.0, 0.0, 1.0), (0.5, 0.0, -0.25))
FAST = RetryPolicy(retries=3, base_s=0.01, cap_s=0.05)  # the real backoff, with short waits


def write_pairs(folder: Path, n: int, with_reference: bool = False) -> Path:
    """``n`` pairs of small clouds in ``folder`` and a pairs.csv naming them relative to it (no id column)."""
    rng = np.random.default_rng(0)
    (folder / "clouds").mkdir(exist_ok=True)
    rows = ["source,target,T_target_source,comment" if with_reference else "source,target"]
    for i in range(n):
        source = rng.normal(size=(50, 3))
        write_point_cloud(folder / "clouds" / f"s{i}.ply", source)
        write_point_cloud(folder / "clouds" / f"t{i}.ply", source @ T_KNOWN[:3, :3].T + T_KNOWN[:3, 3])
        row = f"clouds/s{i}.ply,clouds/t{i}.ply"
        if with_reference:  # the reference, and an extra column with a quoted comma (ignored)
            row += f',{" ".join(f"{x:.17g}" for x in T_KNOWN.ravel())},"a, quoted note"'
        rows.append(row)
    path = folder / "pairs.csv"
    path.write_text("\n".join(rows) + "\n")
    return path


def lines_of(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


# --- the pairs file -----------------------------------------------------------------------------------------


def test_pairs_paths_ids_and_reference(tmp_path: Path) -> None:
    pairs = read_pairs(write_pairs(tmp_path, 3, with_reference=True))
    assert [p.id for p in pairs] == [f"clouds/s{i}.ply->clouds/t{i}.ply" for i in range(3)]  # derived: stable
    assert [p.index for p in pairs] == [0, 1, 2]
    assert pairs[1].source == tmp_path / "clouds" / "s1.ply" and pairs[1].source.exists()
    assert_allclose(pairs[2].T_target_source, T_KNOWN)


def test_the_real_scan_pairs_file_reads_as_it_is(scans_dir: Path) -> None:
    pairs = read_pairs(scans_dir / "pairs.csv")
    assert len(pairs) >= 15 and len({p.id for p in pairs}) == len(pairs)
    assert all(p.source.exists() and p.target.exists() for p in pairs)
    assert all(p.T_target_source is not None and np.allclose(p.T_target_source[3], [0, 0, 0, 1]) for p in pairs)
    assert pairs[0].id == "bunny_bun000_to_bun045"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("src,tgt\na,b\n", "needs the columns source and target (it has: src, tgt)"),
        ("source,target\na.ply,\n", "line 2: source and target must not be empty"),
        ("id,source,target\nx,a.ply,b.ply\nx,c.ply,d.ply\n", "line 3: id 'x' repeats line 2"),
        ("source,target,T_target_source\na.ply,b.ply,1 2 3\n", "line 2: T_target_source must be 16 numbers"),
    ],
)
def test_bad_pairs_files_say_where(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "pairs.csv"
    path.write_text(text)
    with pytest.raises(PairsFileError, match=re.escape(message)):
        read_pairs(path)


def test_shards_partition_the_pairs(tmp_path: Path) -> None:
    pairs = read_pairs(write_pairs(tmp_path, 10))
    shards = [shard(pairs, i, 3) for i in range(3)]
    assert [[p.index for p in s] for s in shards] == [[0, 3, 6, 9], [1, 4, 7], [2, 5, 8]]
    with pytest.raises(ValueError, match="need 0 <= index < count"):
        shard(pairs, 3, 3)


# --- the results file ---------------------------------------------------------------------------------------


def test_a_partial_last_line_is_cut_and_its_pair_runs_again(tmp_path: Path) -> None:
    out = tmp_path / "results.jsonl"
    out.write_text('{"id": "a", "ok": true}\n{"id": "b", "ok": false}\n{"id": "c", "ok": tr')
    assert set(read_results(out)) == {"a", "b"}
    assert out.read_text() == '{"id": "a", "ok": true}\n{"id": "b", "ok": false}\n'
    out.write_text('{"id": "a", "ok": true}\nnot json\n')
    with pytest.raises(ResultsFileError, match="line 2"):
        read_results(out)


def test_reference_error_against_a_known_offset() -> None:
    off = T_KNOWN.copy()
    off[:3, :3] = make_transform(3.0, (1.0, 1.0, 0.0), (0.0, 0.0, 0.0))[:3, :3] @ T_KNOWN[:3, :3]
    off[:3, 3] += [0.003, 0.004, 0.0]
    err = reference_error(off, T_KNOWN)
    assert err["rotation_deg"] == pytest.approx(3.0) and err["translation"] == pytest.approx(0.005)


# --- retries, over real HTTP (a canned loopback service) ----------------------------------------------------


def answer_after(failures: list[tuple[int, Any]]):
    """A /register handler: the given (status, body) answers first, then the canned 200."""
    queue = list(failures)
    lock = threading.Lock()

    def handler(_body: Any) -> tuple[int, Any]:
        with lock:
            return queue.pop(0) if queue else (200, {**canned_response(T_KNOWN), "status": "converged"})

    return handler


def test_503_and_502_are_retried_then_registered(fake_service, tmp_path: Path) -> None:
    fake_service.routes[("POST", "/register")] = answer_after([(503, {"detail": "busy"}), (502, "bad gateway")])
    out = tmp_path / "results.jsonl"
    with PranetClient(fake_service.url) as client:
        summary = client.register_many(write_pairs(tmp_path, 1), out, concurrency=1, retry=FAST)
    assert len(fake_service.requests) == 3
    (line,) = lines_of(out)
    assert line["ok"] and line["attempts"] == 3 and line["status"] == "converged"
    assert_allclose(line["transform"], T_KNOWN)
    assert summary.exit_code == 0 and summary.registered == 1


@pytest.mark.parametrize("status", [400, 404, 413, 422, 500, 504])
def test_other_errors_are_not_retried_and_are_recorded(fake_service, tmp_path: Path, status: int) -> None:
    fake_service.routes[("POST", "/register")] = answer_after([(status, {"detail": "no: because"})])  # then 200
    out = tmp_path / "results.jsonl"
    with PranetClient(fake_service.url) as client:
        summary = client.register_many(write_pairs(tmp_path, 1), out, retry=FAST)
    assert len(fake_service.requests) == 1
    (line,) = lines_of(out)
    assert not line["ok"] and line["http_status"] == status and "no: because" in line["error"]
    assert summary.exit_code == 3
    # A rerun skips the recorded error; --retry-errors runs it again (the new line follows the old one).
    with PranetClient(fake_service.url) as client:
        again = client.register_many(out.parent / "pairs.csv", out, retry=FAST)
        assert (again.skipped, again.failed_before, again.exit_code) == (1, 1, 3) and len(lines_of(out)) == 1
        client.register_many(out.parent / "pairs.csv", out, retry=FAST, retry_errors=True)
    assert [line["ok"] for line in lines_of(out)] == [False, True]


def test_retries_wait_longer_each_time_and_at_least_retry_after() -> None:
    policy = RetryPolicy(retries=5, base_s=1.0, cap_s=8.0)
    rng = np.random.default_rng(0)
    busy = PranetError("busy", 503)
    waits = np.array([[policy.delay(k, busy, rng) for k in range(5)] for _ in range(2000)])
    assert np.all(waits >= 0) and np.all(waits <= [1, 2, 4, 8, 8])
    assert_allclose(waits.mean(axis=0), [0.5, 1, 2, 4, 4], rtol=0.1)  # full jitter: uniform up to the bound
    assert policy.delay(0, PranetError("busy", 503, retry_after=3.0), rng) >= 3.0


def test_an_unreachable_service_leaves_the_pairs_for_the_next_run(tmp_path: Path) -> None:
    out = tmp_path / "results.jsonl"
    pairs = write_pairs(tmp_path, 6)
    with PranetClient(f"http://127.0.0.1:{free_port()}", timeout=2.0) as client:
        summary = client.register_many(pairs, out, concurrency=2, retry=FAST)
    assert not out.read_text()  # no line: retryable failures are not final
    assert summary.not_done == 6 and summary.exit_code == 4
    assert summary.stopped and "in a row got no answer" in summary.stopped  # 2 in a row: it stopped sending


def test_an_unreadable_file_is_recorded_and_the_others_run(fake_service, tmp_path: Path) -> None:
    fake_service.routes[("POST", "/register")] = answer_after([])
    pairs = write_pairs(tmp_path, 3)
    (tmp_path / "clouds" / "t1.ply").write_text("not a ply\n")
    out = tmp_path / "results.jsonl"
    with PranetClient(fake_service.url) as client:
        summary = client.register_many(pairs, out, retry=FAST)
    by_id = {line["id"]: line for line in lines_of(out)}
    assert [by_id[f"clouds/s{i}.ply->clouds/t{i}.ply"]["ok"] for i in range(3)] == [True, False, True]
    assert "not a valid PLY" in by_id["clouds/s1.ply->clouds/t1.ply"]["error"]
    assert summary.exit_code == 3 and len(fake_service.requests) == 2


# --- killed and resumed -------------------------------------------------------------------------------------


def run_killed_then_resumed(args: list[str], out: Path, kill_after: int) -> tuple[int, subprocess.CompletedProcess]:
    """``pranet-client register-many *args``: SIGKILL once ``out`` has ``kill_after`` lines, then run it again
    to the end. Returns (lines when killed, the second run)."""
    cmd = [console_script("pranet-client"), "register-many", *args]
    first = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=clean_env())
    deadline = time.monotonic() + 300
    try:
        while first.poll() is None and time.monotonic() < deadline:
            if out.exists() and out.read_text().count("\n") >= kill_after:
                break
            time.sleep(0.02)
        assert first.poll() is None, f"the run ended before it was killed: {first.stderr.read().decode()[-2000:]}"
        first.send_signal(signal.SIGKILL)
    finally:
        first.wait(timeout=30)
        first.stderr.close()
    lines_at_kill = out.read_text().count("\n")
    second = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=clean_env())
    return lines_at_kill, second


def test_killed_with_sigkill_and_resumed_every_pair_once(fake_service, tmp_path: Path) -> None:
    def slow(_body: Any) -> tuple[int, Any]:
        time.sleep(0.05)
        return 200, {**canned_response(T_KNOWN), "status": "converged"}

    fake_service.routes[("POST", "/register")] = slow
    pairs, out = write_pairs(tmp_path, 40), tmp_path / "results.jsonl"
    args = [str(pairs), "--out", str(out), "--concurrency", "3", "--url", fake_service.url]
    lines_at_kill, second = run_killed_then_resumed(args, out, kill_after=10)
    assert second.returncode == 0, second.stderr
    ids = Counter(line["id"] for line in lines_of(out))
    assert set(ids) == {p.id for p in read_pairs(pairs)} and set(ids.values()) == {1}
    assert 10 <= lines_at_kill < 40
    assert f"{lines_at_kill} skipped" in second.stderr
    # At most the pairs in flight were lost: every pair answered before the kill is in the file.
    assert len(fake_service.requests) - 40 <= 3


def test_cli_shards_write_disjoint_parts(fake_service, tmp_path: Path) -> None:
    fake_service.routes[("POST", "/register")] = answer_after([])
    pairs = write_pairs(tmp_path, 7)
    seen: list[str] = []
    for i in range(3):
        out = tmp_path / f"results-{i}.jsonl"
        proc = run_console(
            "pranet-client", "register-many", pairs, "--out", out, "--shard-index", str(i), "--shard-count", "3",
            "--url", fake_service.url, "--quiet",
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        seen += [line["id"] for line in lines_of(out)]
    assert sorted(seen) == sorted(p.id for p in read_pairs(pairs))
    proc = run_console(
        "pranet-client", "register-many", pairs, "--out", out, "--shard-index", "3", "--shard-count", "3"
    )
    assert proc.returncode == 1 and "must be less than --shard-count" in proc.stderr


@pytest.mark.slow
def test_real_scans_end_to_end_killed_and_resumed(pranet_server, scans_dir: Path, tmp_path: Path) -> None:
    """The real pairs.csv against pranet-serve with the shipped model, killed halfway with SIGKILL and resumed.

    Bounded for CI: ICP only from the input pose (``--steps 0,0 --no-rescue``: about 1 s a pair here); the batch
    machinery is the subject, not the registration's accuracy."""
    pairs = read_pairs(scans_dir / "pairs.csv")
    out = tmp_path / "results.jsonl"
    args = [str(scans_dir / "pairs.csv"), "--out", str(out), "--concurrency", "2", "--url", pranet_server.url]
    args += ["--steps", "0,0", "--no-rescue"]
    lines_at_kill, second = run_killed_then_resumed(args, out, kill_after=len(pairs) // 2)
    assert second.returncode == 0, second.stderr
    lines = lines_of(out)
    assert Counter(line["id"] for line in lines) == Counter(p.id for p in pairs)  # every pair exactly once
    assert f"{lines_at_kill} skipped" in second.stderr and "median rotation error" in second.stderr
    by_id = {p.id: p for p in pairs}
    for line in lines:
        assert line["ok"] and line["status"] in ("converged", "suspect"), line
        T = np.asarray(line["transform"])
        assert_allclose(T[3], [0, 0, 0, 1]) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
        reference = by_id[line["id"]].T_target_source
        R_delta = reference[:3, :3].T @ T[:3, :3]
        assert line["reference_error"]["rotation_deg"] == pytest.approx(np.degrees(rotation_angle(R_delta)))
        assert line["n_source"] > 1000 and line["timing_ms"]["total"] > 0 and line["attempts"] == 1
