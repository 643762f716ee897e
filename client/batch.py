"""Batch registration: the pairs of a CSV file through one service, into a JSON-lines file, resumable.

    with PranetClient(url) as client:
        summary = client.register_many("pairs.csv", "results.jsonl", concurrency=4)

The CSV has the columns ``source`` and ``target`` (cloud files, relative to the CSV's folder unless absolute),
optionally ``id`` and ``T_target_source`` (16 numbers, row-major: the reference transform); other columns are
ignored, so the real-scan ``pairs.csv`` works as it is. Without an ``id`` column a pair's id is
``"<source>-><target>"`` as written in the CSV.

One JSON line per pair is appended, flushed and fsync'ed as its answer arrives, so a killed run loses at most the
pairs in flight, and a rerun skips every id already in the file. A pair gets a line when it is registered
(``"ok": true``) or when it failed for good (``"ok": false``: a 4xx, an unreadable file, a 5xx other than
502/503). 502, 503 and connection errors are retried with exponential backoff; a pair that still fails gets no
line, so the next run does it. ``shard_index``/``shard_count`` select the pairs ``i % shard_count ==
shard_index`` (``i``: the pair's row in the CSV, from 0), for several processes or a Kubernetes Indexed Job.
"""

from __future__ import annotations

import csv
import json
import os
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np
import numpy.typing as npt

from pranet.client.client import PranetConnectionError, PranetError, RegistrationResult
from pranet.client.io import PointCloudIOError, read_point_cloud
from pranet.core.se3 import rotation_angle

if TYPE_CHECKING:
    from pranet.client.client import PranetClient

Array = npt.NDArray[np.float64]

RETRY_STATUSES = frozenset({502, 503})  # "try again": a proxy without a live upstream, a full or loading service
DEFAULT_RETRIES = 5
BACKOFF_BASE_S = 0.5  # the first retry waits up to this long; each next one up to twice as long ...
BACKOFF_CAP_S = 30.0  # ... up to this


class PairsFileError(ValueError):
    """The pairs CSV cannot be used (missing columns, a bad row); the message names the file and the line."""


class ResultsFileError(ValueError):
    """The results file is not one this module wrote (a line that is not a JSON object with an id)."""


@dataclass(frozen=True, eq=False)  # eq=False: pairs are compared by id, never by their arrays
class Pair:
    id: str
    source: Path
    target: Path
    index: int = 0  # the pair's row among the CSV's data rows, from 0: the shard key
    T_target_source: Array | None = None  # the reference transform, when the CSV gives one


def read_pairs(path: str | os.PathLike[str]) -> list[Pair]:
    """The pairs of a CSV file (see the module's docstring); raises ``PairsFileError``."""
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            columns = [c.strip() for c in reader.fieldnames or []]
            missing = [c for c in ("source", "target") if c not in columns]
            if missing:
                raise PairsFileError(
                    f"{path}: needs the columns source and target (it has: {', '.join(columns) or 'no header'})"
                )
            rows = [({(k or "").strip(): (v or "").strip() for k, v in row.items()}, reader.line_num) for row in reader]
    except OSError as e:
        raise PairsFileError(f"{path}: {e.strerror or e}") from None
    except (UnicodeDecodeError, csv.Error) as e:
        raise PairsFileError(f"{path}: not a readable CSV file ({e})") from None
    pairs: list[Pair] = []
    seen: dict[str, int] = {}
    for index, (row, line) in enumerate(rows):
        pair = _pair_of(row, index, path, line)
        if pair.id in seen:
            raise PairsFileError(f"{path}, line {line}: id {pair.id!r} repeats line {seen[pair.id]}")
        seen[pair.id] = line
        pairs.append(pair)
    return pairs


def _pair_of(row: dict[str, str], index: int, path: Path, line: int) -> Pair:
    where = f"{path}, line {line}"
    if not row.get("source") or not row.get("target"):
        raise PairsFileError(f"{where}: source and target must not be empty")
    folder = path.parent
    reference = None
    if row.get("T_target_source"):
        try:
            reference = np.array([float(x) for x in row["T_target_source"].split()], dtype=np.float64).reshape(4, 4)
        except ValueError:
            raise PairsFileError(f"{where}: T_target_source must be 16 numbers (a 4x4 matrix, row-major)") from None
    return Pair(
        id=row.get("id") or f"{row['source']}->{row['target']}",
        source=folder / row["source"],  # an absolute path stays as it is
        target=folder / row["target"],
        index=index,
        T_target_source=reference,
    )


def shard(pairs: Sequence[Pair], shard_index: int = 0, shard_count: int = 1) -> list[Pair]:
    """The pairs ``i % shard_count == shard_index``, ``i`` being a pair's row in the CSV."""
    if shard_count < 1 or not 0 <= shard_index < shard_count:
        raise ValueError(f"shard index {shard_index} of {shard_count}: need 0 <= index < count")
    return [p for p in pairs if p.index % shard_count == shard_index]


# --- the results file ---------------------------------------------------------------------------------------


def read_results(path: Path) -> dict[str, dict[str, Any]]:
    """``{id: record}`` of a results file (the last line of an id wins); a missing file is empty.

    A last line without its newline is the trace of a killed write: it is cut off the file (its pair runs again).
    """
    if not path.exists():
        return {}
    _drop_partial_last_line(path)
    records: dict[str, dict[str, Any]] = {}
    with open(path, encoding="utf-8") as f:
        for number, text in enumerate(f, 1):
            if not text.strip():
                continue
            try:
                record = json.loads(text)
            except ValueError:
                record = None
            if not isinstance(record, dict) or not isinstance(record.get("id"), str):
                raise ResultsFileError(f"{path}, line {number}: not a register-many result (a JSON object with an id)")
            records[record["id"]] = record
    return records


def _drop_partial_last_line(path: Path) -> None:
    with open(path, "rb+") as f:
        size = f.seek(0, os.SEEK_END)
        if size == 0:
            return
        f.seek(size - 1)
        if f.read(1) == b"\n":
            return
        # Read back from the end to the last newline; only the partial line is scanned.
        end = size
        while end > 0:
            start = max(0, end - 65536)
            f.seek(start)
            cut = f.read(end - start).rfind(b"\n")
            if cut >= 0:
                f.truncate(start + cut + 1)
                return
            end = start
        f.truncate(0)


class ResultsWriter:
    """Appends one JSON line per record and makes it durable before returning (flush + fsync)."""

    def __init__(self, path: Path):
        self.path = path
        self._file: TextIO = open(path, "a", encoding="utf-8")  # noqa: SIM115 - closed by close()

    def write(self, record: dict[str, Any]) -> None:
        self._file.write(json.dumps(record, separators=(",", ":")) + "\n")
        self._file.flush()
        os.fsync(self._file.fileno())

    def close(self) -> None:
        self._file.close()


# --- one pair -----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RetryPolicy:
    """``retries`` more attempts after the first, on 502/503 and connection errors, never on other statuses.

    The k-th retry waits a uniform random time in ``[0, min(cap, base * 2**k)]`` ("full jitter", so that clients
    refused together do not come back together), and at least what the server's ``Retry-After`` asked for.
    """

    retries: int = DEFAULT_RETRIES
    base_s: float = BACKOFF_BASE_S
    cap_s: float = BACKOFF_CAP_S

    @staticmethod
    def retryable(error: PranetError) -> bool:
        return isinstance(error, PranetConnectionError) or error.status_code in RETRY_STATUSES

    def delay(self, retry: int, error: PranetError, rng: np.random.Generator) -> float:
        wait_s = float(rng.uniform(0.0, min(self.cap_s, self.base_s * 2.0**retry)))
        return max(wait_s, error.retry_after or 0.0)


@dataclass
class Outcome:
    """One pair's request: the result, or the error that ended it; ``gave_up``: retries spent on a retryable one."""

    result: RegistrationResult | None
    error: PranetError | None
    attempts: int
    request_ms: float  # from the first attempt to the answer, the retries' waits included

    @property
    def gave_up(self) -> bool:
        return self.error is not None and RetryPolicy.retryable(self.error)


def register_with_retries(
    client: PranetClient,
    source: Array,
    target: Array,
    options: dict[str, Any],
    retry: RetryPolicy,
    rng: np.random.Generator,
) -> Outcome:
    """``client.register``, retried as ``retry`` says."""
    t0 = time.perf_counter()
    for attempt in range(retry.retries + 1):
        try:
            return Outcome(client.register(source, target, **options), None, attempt + 1, _ms_since(t0))
        except PranetError as e:
            if not retry.retryable(e) or attempt == retry.retries:
                return Outcome(None, e, attempt + 1, _ms_since(t0))
            time.sleep(retry.delay(attempt, e, rng))
    raise AssertionError("unreachable: the last attempt returns")


def _base_record(pair: Pair) -> dict[str, Any]:
    return {"id": pair.id, "source": str(pair.source), "target": str(pair.target)}


def ok_record(pair: Pair, result: RegistrationResult, attempts: int, client_ms: dict[str, float]) -> dict[str, Any]:
    record = {
        **_base_record(pair),
        "ok": True,
        "transform": result.transform.tolist(),  # T_target_source: target ≈ R @ source + t, the clouds' units
        "status": result.status,
        "confidence": result.confidence,
        "rescued": result.rescued,
        "candidate": result.candidate,
        "n_source": result.n_source,
        "n_target": result.n_target,
        "timing_ms": result.timing_ms,  # the server's, per stage
        "client_ms": client_ms,  # reading the files, and the request with its retries
        "attempts": attempts,
        "model": result.model,
    }
    if pair.T_target_source is not None:
        record["reference_error"] = reference_error(result.transform, pair.T_target_source)
    return record


def error_record(pair: Pair, message: str, http_status: int | None, attempts: int, client_ms: dict) -> dict[str, Any]:
    return {
        **_base_record(pair),
        "ok": False,
        "error": message,
        "http_status": http_status,
        "attempts": attempts,
        "client_ms": client_ms,
    }


def reference_error(T: Array, T_reference: Array) -> dict[str, float]:
    """Rotation error (degrees) and translation error (the clouds' units) of ``T`` against the reference."""
    R_delta = T_reference[:3, :3].T @ T[:3, :3]
    return {
        "rotation_deg": float(np.degrees(rotation_angle(R_delta))),
        "translation": float(np.linalg.norm(T[:3, 3] - T_reference[:3, 3])),
    }


# --- the run ------------------------------------------------------------------------------------------------


@dataclass
class BatchSummary:
    """What one ``register_many`` run did; ``exit_code`` is the CLI's exit status."""

    out: Path
    total: int  # pairs of this shard
    skipped: int = 0  # already in the results file
    failed_before: int = 0  # of those, pairs whose line is an error
    registered: int = 0
    failed: int = 0  # an error line written (not retried)
    not_done: int = 0  # retries spent on 502/503/connection errors: no line; the next run does them
    stopped: str | None = None  # why the run stopped early
    statuses: Counter = field(default_factory=Counter)  # "converged" / "suspect"
    seconds: float = 0.0
    server_ms: list[float] = field(default_factory=list)
    rotation_errors_deg: list[float] = field(default_factory=list)
    translation_errors: list[float] = field(default_factory=list)

    @property
    def done(self) -> int:
        return self.registered + self.failed

    @property
    def exit_code(self) -> int:
        """0: every pair registered; 3: some pairs failed for good (see their lines); 4: some pairs are not done
        (the service was unavailable): run again to resume."""
        return 4 if self.not_done or self.stopped else 3 if self.failed or self.failed_before else 0

    def add(self, record: dict[str, Any]) -> None:
        if not record["ok"]:
            self.failed += 1
            return
        self.registered += 1
        self.statuses[record.get("status")] += 1
        if "total" in record.get("timing_ms", {}):
            self.server_ms.append(float(record["timing_ms"]["total"]))
        if "reference_error" in record:
            self.rotation_errors_deg.append(record["reference_error"]["rotation_deg"])
            self.translation_errors.append(record["reference_error"]["translation"])

    def counts(self) -> str:
        """E.g. "9 converged, 4 suspect, 1 failed, 1 skipped"."""
        parts = [f"{self.statuses[s]} {s}" for s in ("converged", "suspect") if self.statuses[s]]
        for n, what in (
            (self.failed, "failed"),
            (self.not_done, "not done"),
            (self.skipped, "skipped"),
            (self.failed_before, "of them failed earlier"),
        ):
            if n:
                parts.append(f"{n} {what}")
        return ", ".join(parts) or "none yet"

    def progress_line(self) -> str:
        todo = self.total - self.skipped
        handled = self.done + self.not_done
        rate = handled / self.seconds if self.seconds > 0 else 0.0
        left = f", about {(todo - handled) / rate:.0f} s left" if rate > 0 and handled < todo else ""
        return f"{handled + self.skipped}/{self.total} pairs ({self.counts()}), {rate:.2f} pairs/s{left}"

    def report(self) -> str:
        """The summary printed at the end of a run."""
        lines = [f"{self.total} pairs in this shard: {self.counts()}"]
        ran = self.done + self.not_done
        if ran:
            lines.append(f"{ran} ran in {self.seconds:.1f} s ({ran / self.seconds:.2f} pairs/s)")
        if self.server_ms:
            lines.append(f"server time per pair: median {np.median(self.server_ms):.0f} ms")
        if self.rotation_errors_deg:
            lines.append(
                f"against T_target_source ({len(self.rotation_errors_deg)} pairs): median rotation error "
                f"{np.median(self.rotation_errors_deg):.3g} deg, translation {np.median(self.translation_errors):.3g}"
            )
        if self.stopped:
            lines.append(f"stopped: {self.stopped}")
        if self.not_done or self.stopped:
            lines.append("run the same command again to resume: pairs already in the results file are skipped")
        if self.failed or self.failed_before:
            lines.append(
                f"{self.failed + self.failed_before} pairs failed: see their 'error' in {self.out} "
                "(--retry-errors runs them again)"
            )
        lines.append(f"results: {self.out}")
        return "\n".join(lines)


class Progress:
    """One line on stderr: rewritten in place on a terminal, else printed every ``every_s`` seconds."""

    def __init__(self, stream: TextIO | None = None, every_s: float = 10.0):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.every_s = every_s
        self._last = -np.inf

    def __call__(self, summary: BatchSummary, final: bool = False) -> None:
        now = time.monotonic()
        if self.tty:
            self.stream.write(f"\r\x1b[Kregister-many: {summary.progress_line()}" + ("\n" if final else ""))
        elif final or now - self._last >= self.every_s:
            self.stream.write(f"register-many: {summary.progress_line()}\n")
            self._last = now
        self.stream.flush()


def register_many(
    client: PranetClient,
    pairs: str | os.PathLike[str] | Sequence[Pair],
    out: str | os.PathLike[str],
    concurrency: int = 4,
    *,
    retry: RetryPolicy | None = None,
    shard_index: int = 0,
    shard_count: int = 1,
    retry_errors: bool = False,
    progress: bool | Callable[[BatchSummary, bool], None] = False,
    jitter_seed: int = 0,
    **options: Any,
) -> BatchSummary:
    """Register every pair of ``pairs`` (a CSV path, or ``Pair`` objects) not yet in ``out``; see the module.

    ``concurrency`` pairs are in flight at once; ``retry`` says when and how often to retry (default: 5 times).
    ``retry_errors`` runs again the pairs whose line is an error (their new line follows the old one; the last
    line of an id wins). ``progress``: ``True`` for a line on stderr, or a callable ``(summary, final)``.
    ``jitter_seed`` seeds the retries' jitter. ``options`` go to ``client.register`` (``icp``, ``init``,
    ``policy``, ...).
    """
    if concurrency < 1:
        raise ValueError(f"concurrency must be >= 1, got {concurrency}")
    retry = retry or RetryPolicy()
    report = Progress() if progress is True else progress or None
    chosen = shard(
        read_pairs(pairs) if isinstance(pairs, (str, os.PathLike)) else list(pairs), shard_index, shard_count
    )
    out = Path(out)
    previous = read_results(out)
    kept = [previous[p.id] for p in chosen if _already_done(previous.get(p.id), retry_errors)]
    todo = [p for p in chosen if not _already_done(previous.get(p.id), retry_errors)]
    summary = BatchSummary(out=out, total=len(chosen), skipped=len(kept))
    summary.failed_before = sum(1 for record in kept if not record.get("ok"))
    writer = ResultsWriter(out)
    t0 = time.perf_counter()
    try:
        for record in _run(client, todo, concurrency, retry, jitter_seed, options, summary):
            if record is not None:
                writer.write(record)
                summary.add(record)
            summary.seconds = time.perf_counter() - t0
            if report:
                report(summary, False)
    finally:
        writer.close()
        summary.seconds = time.perf_counter() - t0
    if report:
        report(summary, True)
    return summary


def _already_done(record: dict[str, Any] | None, retry_errors: bool) -> bool:
    return record is not None and (record.get("ok") is True or not retry_errors)


def _run(
    client: PranetClient,
    todo: list[Pair],
    concurrency: int,
    retry: RetryPolicy,
    jitter_seed: int,
    options: dict[str, Any],
    summary: BatchSummary,
) -> Iterator[dict[str, Any] | None]:
    """Yield each pair's record as its answer arrives (``None`` for a pair given up on: retries spent).

    Files are read here, in the calling thread, just before their pair is sent: at most ``concurrency`` pairs of
    clouds are in memory, and the reader's capture of Open3D's native stderr never overlaps another thread's
    output. Stops sending new pairs once ``concurrency`` pairs in a row were given up on (the service is gone).
    """
    pending = iter(todo)
    in_flight: dict[Future[Outcome], tuple[Pair, float]] = {}
    given_up_in_a_row = 0
    with ThreadPoolExecutor(max_workers=concurrency, thread_name_prefix="register-many") as pool:
        try:
            while True:
                while len(in_flight) < concurrency and summary.stopped is None:
                    pair = next(pending, None)
                    if pair is None:
                        break
                    t0 = time.perf_counter()
                    try:
                        source, target = read_point_cloud(pair.source), read_point_cloud(pair.target)
                    except PointCloudIOError as e:
                        yield error_record(pair, str(e), None, 0, {"read": _ms_since(t0)})
                        continue
                    rng = np.random.default_rng((jitter_seed, pair.index))
                    future = pool.submit(register_with_retries, client, source, target, options, retry, rng)
                    in_flight[future] = (pair, _ms_since(t0))
                if not in_flight:
                    break
                finished, _ = wait(in_flight, return_when=FIRST_COMPLETED)
                for future in finished:
                    pair, read_ms = in_flight.pop(future)
                    outcome = future.result()
                    if outcome.gave_up:
                        summary.not_done += 1
                        given_up_in_a_row += 1
                        if given_up_in_a_row >= concurrency and summary.stopped is None:
                            summary.stopped = f"{given_up_in_a_row} pairs in a row got no answer ({outcome.error})"
                        yield None
                    else:
                        given_up_in_a_row = 0
                        yield _record_of(pair, outcome, read_ms)
        finally:  # interrupted: the pairs in flight finish (their answers are dropped) before the pool closes
            for future in in_flight:
                future.cancel()
    summary.not_done += sum(1 for _ in pending)  # never sent, after a stop


def _record_of(pair: Pair, outcome: Outcome, read_ms: float) -> dict[str, Any]:
    client_ms = {"read": read_ms, "request": outcome.request_ms}
    if outcome.result is not None:
        return ok_record(pair, outcome.result, outcome.attempts, client_ms)
    assert outcome.error is not None
    return error_record(pair, str(outcome.error), outcome.error.status_code, outcome.attempts, client_ms)


def _ms_since(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3
