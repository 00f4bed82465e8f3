"""Stores as they are and as they fail (issue 32): HTTP servers without range requests, hosts that cannot be
reached, and an S3 store behind a proxy that refuses, stalls, cuts a connection or answers an error status at
a chosen request (``storeproxy.py``). Every case ends with the documented exit code and one line, leaves
nothing in the store or locally, and no run outlives its fault by more than 30 s (a watchdog: the
subprocess's own timeout, not a sleep).
"""

from __future__ import annotations

import faulthandler
import os
import signal
import subprocess
import threading
import time
import warnings
from pathlib import Path

import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream.errors import InputNotFound, PrismWarning, StorageError
from prism_stream.run import remote, staging
from prism_stream.run.inputs import open_sources

from conftest import edge_file, prism_stream_command, real_file, user_env
from storeproxy import FileServer

AUTZEN = real_file("pdal__autzen_trim.las")
PDAL_PARQUET = edge_file("pdal__1.2-with-color.parquet")
WATCHDOG = 30  # seconds a run may outlive its fault


class Hung(Exception):
    pass


@pytest.fixture(autouse=True)
def hang_watchdog():
    """A run that hangs in this process (the reported hang: an error, then a wait that never ends) would hang
    the suite: past three watchdogs the test fails with the stack of where it waited (SIGALRM), and past four
    (a wait no signal handler reaches) the test's process dumps its threads' stacks and exits, which fails
    the test too (pytest-xdist reports its worker as crashed and starts another)."""
    def hung(signum, frame):
        raise Hung(f"the test outlived {3 * WATCHDOG} s: a run hung")

    before = signal.signal(signal.SIGALRM, hung)
    signal.alarm(3 * WATCHDOG)
    faulthandler.dump_traceback_later(4 * WATCHDOG, exit=True)
    yield
    faulthandler.cancel_dump_traceback_later()
    signal.alarm(0)
    signal.signal(signal.SIGALRM, before)


@pytest.fixture(autouse=True)
def quick_backoff(monkeypatch):
    """HTTP's tries a twentieth of a second apart here (the suite's time), not half a second."""
    monkeypatch.setattr(remote, "HTTP_BACKOFF", 0.025)


def _fail_after_solve(monkeypatch, proxy, fault: str) -> None:
    """The store's range reads fail from the solve on: a run reading twice meets it in pass two."""
    from prism_stream.engines import pipeline

    real = pipeline.solve

    def solve_then_fail(*a, **kw):
        proxy.arm("range", fault)
        return real(*a, **kw)

    monkeypatch.setattr(pipeline, "solve", solve_then_fail)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """The same folder on two servers: one with range requests, one without (``python -m http.server``'s way)."""
    folder = tmp_path_factory.mktemp("www")
    prism_stream.sample(str(AUTZEN), str(folder / "scan.laz"), ratio=1.0)
    (folder / "cloud.parquet").write_bytes(PDAL_PARQUET.read_bytes())
    with_ranges, without = FileServer(folder, ranges=True), FileServer(folder, ranges=False)
    yield folder, with_ranges.url, without.url
    with_ranges.close()
    without.close()


def _forget_copies():
    remote.drop_copies()
    remote._RANGED.clear()


@pytest.mark.parametrize("name", ["scan.laz", "cloud.parquet"])
def test_a_server_without_range_requests_is_copied_then_read(served, tmp_path, name):
    """The file is copied whole to the temporary folder (said in a warning), read as the ranged server's,
    and the copy is gone after the run."""
    folder, ranged, plain = served
    temp = tmp_path / "tmp"
    temp.mkdir()
    _forget_copies()
    outs = []
    for url in (f"{ranged}/{name}", f"{plain}/{name}"):
        out = tmp_path / f"{len(outs)}.parquet"
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            prism_stream.sample(url, str(out), ratio=0.3, temp_dir=str(temp))
        copied = [w for w in seen if issubclass(w.category, PrismWarning) and "no range requests" in str(w.message)]
        assert len(copied) == (url.startswith(plain)), [str(w.message) for w in seen]
        outs.append(pq.read_table(out))
    assert outs[0].equals(outs[1]) and outs[0].num_rows > 0
    assert os.listdir(temp) and all(staging.is_temporary(n) for n in os.listdir(temp))  # the copy, until exit
    remote.drop_copies()
    assert os.listdir(temp) == []


def test_a_server_saying_accept_ranges_none_is_copied_too(served, tmp_path):
    """fsspec opens such a file as a stream, which cannot seek: the probe must not fail on that (exit 70)."""
    folder, ranged, _ = served
    server = FileServer(folder, ranges=False, refuse_ranges=True)
    try:
        _forget_copies()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PrismWarning)
            prism_stream.sample(f"{server.url}/scan.laz", str(tmp_path / "a.parquet"), ratio=0.3)
        prism_stream.sample(f"{ranged}/scan.laz", str(tmp_path / "b.parquet"), ratio=0.3)
        assert pq.read_table(tmp_path / "a.parquet").equals(pq.read_table(tmp_path / "b.parquet"))
    finally:
        server.close()
        _forget_copies()


def test_a_copy_that_does_not_fit_or_a_cluster_run_is_refused_in_one_line(served, tmp_path, monkeypatch):
    folder, _, plain = served
    _forget_copies()
    url = f"{plain}/scan.laz"
    with pytest.raises(StorageError, match="workers cannot share"):
        open_sources([url], copies_to=None, refuse_copies="a cluster's workers cannot share one local copy")
    monkeypatch.setattr(staging, "free_bytes", lambda folder: staging.RESERVE + 10)
    with pytest.raises(StorageError, match="does not fit in") as caught:
        prism_stream.sample(url, str(tmp_path / "out.parquet"), ratio=0.3, temp_dir=str(tmp_path))
    assert str(caught.value).startswith(url) and "\n" not in str(caught.value)
    assert not (tmp_path / "out.parquet").exists() and not [n for n in os.listdir(tmp_path)
                                                             if staging.is_temporary(n)]


def test_missing_unreachable_and_failing_http_hosts_are_told_apart(served, tmp_path):
    """A 404 is a missing file (exit 3); a refused connection, an unknown host or a 5xx is the store's failure
    (exit 10, as for S3), decided by the exception types and the status, not by words."""
    _, ranged, _ = served
    with pytest.raises(InputNotFound):
        prism_stream.sample(f"{ranged}/missing.laz", str(tmp_path / "a.parquet"), ratio=0.1)
    for url in ("http://127.0.0.1:9/scan.laz", "http://host.invalid/scan.laz"):  # nothing listens; no such name
        with pytest.raises(StorageError, match="could not be reached"):
            prism_stream.sample(url, str(tmp_path / "a.parquet"), ratio=0.1)
    started = time.monotonic()
    done = subprocess.run([*prism_stream_command(), "http://127.0.0.1:9/scan.laz", str(tmp_path / "b.parquet"),
                           "--ratio", "0.1"], capture_output=True, text=True, timeout=WATCHDOG, env=user_env())
    assert done.returncode == 10, done.stderr
    assert done.stderr.count("\n") == 1 and "could not be reached" in done.stderr, done.stderr
    assert time.monotonic() - started < WATCHDOG
    assert not list(Path(tmp_path).iterdir())


# -- HTTP servers behind the fault proxy -----------------------------------------------------------------


@pytest.fixture(scope="module")
def http_faults(tmp_path_factory, served):
    """The served LAZ file under a folder (so that requests name a file, not a bucket) on a server with range
    requests and one without, each behind a fault proxy: (ranged proxy, plain proxy)."""
    from storeproxy import FaultProxy

    folder, _, _ = served
    root = tmp_path_factory.mktemp("www-faults")
    (root / "data").mkdir()
    (root / "data" / "scan.laz").write_bytes((folder / "scan.laz").read_bytes())
    servers = [FileServer(root, ranges=True), FileServer(root, ranges=False)]
    proxies = [FaultProxy(server.url) for server in servers]
    yield proxies
    for p in proxies:
        p.close()
    for server in servers:
        server.close()


# (server, operation, nth): the open (its HEAD, the header's range read), pass one (a later range read), and
# the whole-file copy a server without range requests needs
HTTP_AT = [("ranged", "head", 1), ("ranged", "range", 1), ("ranged", "range", 2), ("plain", "read", 1)]


@pytest.mark.parametrize("server,op,nth,fault", [(srv, op, nth, f) for srv, op, nth in HTTP_AT
                                                 for f in ["refuse", "stall", "cut", "status:500"]
                                                 if f != "stall" or (srv, op, nth) != ("ranged", "head", 1)])
def test_a_failing_http_server_is_exit_10_and_leaves_no_copy(http_faults, tmp_path, monkeypatch, server, op, nth,
                                                             fault):
    proxy = http_faults[server == "plain"]  # one try: a slow answer on a busy machine must not end it early
    monkeypatch.setenv(remote.TIMEOUT_VAR, str(STALL if fault == "stall" else 4 * STALL))
    _forget_copies()
    proxy.arm(op, fault, nth)
    url = f"{proxy.url}/data/scan.laz"
    before = _threads()
    try:
        with pytest.raises(prism_stream.PrismError) as caught:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", PrismWarning)  # "copied whole": said before the copy fails
                prism_stream.sample(url, str(tmp_path / "out.parquet"), ratio=0.3, temp_dir=str(tmp_path))
    finally:
        proxy.disarm()
    assert proxy.faulted and time.monotonic() - proxy.tripped_at < WATCHDOG
    assert type(caught.value) is StorageError and caught.value.exit_code == 10, caught.value
    assert str(caught.value).startswith(url + ": ") and "\n" not in str(caught.value)
    if fault == "stall":
        assert f"no answer within {STALL} s" in str(caught.value), caught.value
    assert os.listdir(tmp_path) == []  # no output, no partial copy
    _no_thread_left(before)
    _forget_copies()


@pytest.mark.parametrize("fault", ["refuse", "cut", "status:500"])
def test_a_failing_http_server_in_pass_two_is_exit_10(http_faults, tmp_path, monkeypatch, fault):
    """Reading twice, an HTTP input is read again in pass two: the server fails after the solve."""
    proxy = http_faults[0]
    _fail_after_solve(monkeypatch, proxy, fault)
    _forget_copies()
    url = f"{proxy.url}/data/scan.laz"
    try:
        with pytest.raises(StorageError) as caught:
            prism_stream.sample(url, str(tmp_path / "out.parquet"), ratio=0.3, reads="two", temp_dir=str(tmp_path))
    finally:
        proxy.disarm()
    assert proxy.faulted and time.monotonic() - proxy.tripped_at < WATCHDOG
    assert str(caught.value).startswith(url + ": ") and caught.value.exit_code == 10 and "\n" not in str(caught.value)
    assert os.listdir(tmp_path) == []


# -- an S3 store behind the fault proxy --------------------------------------------------------------------

BUCKET = "scans"
STALL = 2  # PRISM_STREAM_STORE_TIMEOUT in these tests: a stalled request is given up after 2 s a try


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """moto's S3 server behind a fault proxy; the bucket holds an input tile."""
    import boto3
    from moto.server import ThreadedMotoServer

    from storeproxy import FaultProxy

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    upstream = f"http://{host}:{port}"
    client = boto3.client("s3", endpoint_url=upstream, region_name="us-east-1", aws_access_key_id="testing",
                          aws_secret_access_key="testing")
    client.create_bucket(Bucket=BUCKET)
    client.upload_file(str(AUTZEN), BUCKET, "in/autzen.las")
    proxy = FaultProxy(upstream)
    yield proxy, client
    proxy.close()
    server.stop()


def _parquet(path, n: int):
    import numpy as np
    import pyarrow as pa

    rng = np.random.default_rng(3)
    pq.write_table(pa.table({"x": rng.random(n), "y": rng.random(n), "z": rng.random(n),
                             **{c: rng.integers(0, 65536, n).astype(np.uint16) for c in ("red", "green", "blue")}}),
                   path, compression="none")
    return path


@pytest.fixture(scope="module")
def large(tmp_path_factory):
    """A local input whose whole sample (6.6 MB of Parquet) is, in this process (5 MiB parts, below), a multipart
    upload of two parts."""
    return _parquet(tmp_path_factory.mktemp("large") / "large.parquet", 220_000)


@pytest.fixture(scope="module")
def larger(tmp_path_factory):
    """... and one whose sample (12 MB) is a multipart upload for a command line of its own (8 MiB parts)."""
    return _parquet(tmp_path_factory.mktemp("larger") / "larger.parquet", 400_000)


@pytest.fixture
def s3env(store, monkeypatch):
    proxy, client = store
    for name, value in {"AWS_ENDPOINT_URL": proxy.url, "AWS_ACCESS_KEY_ID": "testing",
                        "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1",
                        "AWS_EC2_METADATA_DISABLED": "true", "AWS_SHARED_CREDENTIALS_FILE": os.devnull,
                        "AWS_CONFIG_FILE": os.devnull, remote.TIMEOUT_VAR: str(STALL),
                        "AWS_MAX_ATTEMPTS": "2"}.items():  # the user's own retry setting is kept
        monkeypatch.setenv(name, value)
    for name in ("AWS_PROFILE", "AWS_SESSION_TOKEN", "AWS_ENDPOINT_URL_S3", "AWS_RETRY_MODE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(remote, "UPLOAD_BLOCK", 5 << 20)  # S3's smallest part: a 6.6 MB output is 2 parts
    proxy.disarm()
    yield proxy, client
    proxy.disarm()
    for upload in client.list_multipart_uploads(Bucket=BUCKET).get("Uploads", []):
        client.abort_multipart_upload(Bucket=BUCKET, Key=upload["Key"], UploadId=upload["UploadId"])
    for obj in client.list_objects_v2(Bucket=BUCKET, Prefix="out/").get("Contents", []):
        client.delete_object(Bucket=BUCKET, Key=obj["Key"])


def _left(client) -> tuple[list, list]:
    """(objects under out/, multipart uploads still open)."""
    objects = [o["Key"] for o in client.list_objects_v2(Bucket=BUCKET, Prefix="out/").get("Contents", [])]
    return objects, [u["Key"] for u in client.list_multipart_uploads(Bucket=BUCKET).get("Uploads", [])]


FAULTS = ["refuse", "stall", "cut", "status:503"]
# a stalled request is given up by the client's timeout whatever the request (2 to 10 s a case): it runs once a
# phase (the input's HEAD, a read in pass one and in pass two, the output's check, a part's upload, this one in
# a process of its own); the other faults at every request


def _grid(at: list, stalled: set) -> list:
    return [(op, nth, fault) for op, nth in at for fault in FAULTS if fault != "stall" or (op, nth) in stalled]
# (operation, nth): the store goes down at the nth request of that operation and stays down. The input's open
# (its HEAD, the glob's LIST, the header's range read) and pass one (a later range read of the points)
READ_AT = [("head", 1), ("list", 1), ("range", 1), ("range", 2)]
# the output's publish: a multipart upload's three requests, and the single PUT of an output under one part
WRITE_AT = [("create_multipart", 1), ("upload_part", 2), ("complete_multipart", 1), ("put", 1)]


def _threads() -> set:
    return {t for t in threading.enumerate() if not t.daemon}


def _no_thread_left(before: set) -> None:
    """Every thread the run started that would keep the process alive has ended (within a bounded wait):
    the reported hang was a process that printed its error and then never exited, waiting on one."""
    deadline = time.monotonic() + 10
    while _threads() - before and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _threads() - before, f"threads left running: {sorted(t.name for t in _threads() - before)}"


@pytest.mark.parametrize("op,nth,fault", _grid(READ_AT, {("head", 1), ("range", 2)}))
def test_a_failing_store_under_an_input_is_exit_10_in_bounded_time(s3env, tmp_path, op, nth, fault):
    proxy, client = s3env
    proxy.arm(op, fault, nth)
    out = tmp_path / "out.parquet"
    url = f"s3://{BUCKET}/in/{'*' if op == 'list' else 'autzen'}.las"
    before = _threads()
    with pytest.raises(prism_stream.PrismError) as caught:
        prism_stream.sample(url, str(out), ratio=0.1, temp_dir=str(tmp_path))
    ended = time.monotonic()
    assert proxy.faulted and ended - proxy.tripped_at < WATCHDOG
    assert type(caught.value) is StorageError and caught.value.exit_code == 10, caught.value
    assert str(caught.value).startswith(url + ": ") and "\n" not in str(caught.value)
    if fault == "stall":
        assert f"no answer within {STALL} s" in str(caught.value), caught.value
    assert os.listdir(tmp_path) == []
    _no_thread_left(before)


@pytest.mark.parametrize("op,nth,fault", _grid(WRITE_AT, set()))  # a part's stall: in a process, below
def test_a_failing_store_under_an_output_is_exit_8_and_leaves_nothing(s3env, large, tmp_path, op, nth, fault):
    """Each request of the publish: the run ends with exit 8 in bounded time and no object appears."""
    proxy, client = s3env
    proxy.arm(op, fault, nth)
    url = f"s3://{BUCKET}/out/sample.parquet"
    before = _threads()
    with pytest.raises(prism_stream.PrismError) as caught:  # the whole sample is two parts; 5% one PUT
        prism_stream.sample(str(large), url, ratio=0.05 if op == "put" else 1.0, temp_dir=str(tmp_path))
    ended = time.monotonic()
    assert proxy.faulted and ended - proxy.tripped_at < WATCHDOG, (op, fault)
    assert caught.value.exit_code == 8 and str(caught.value).startswith(url + ": "), caught.value
    assert "\n" not in str(caught.value)
    proxy.disarm()
    objects, uploads = _left(client)
    assert objects == []
    # the store went down mid-upload and stayed down: the abort failed too, and the line says which upload
    # the store keeps (and bills) until someone aborts it
    assert len(uploads) == (op in ("upload_part", "complete_multipart")), uploads
    if uploads:
        assert "could not be aborted" in str(caught.value), caught.value
    assert os.listdir(tmp_path) == []
    _no_thread_left(before)


def test_a_store_refusing_one_kind_of_request_has_the_upload_aborted(s3env, large, tmp_path):
    """A store that still answers (one part refused 20 times: more than the SDK tries) has the upload aborted,
    so no part is left to pay for."""
    proxy, client = s3env
    proxy.arm("upload_part", "status:503", 2, times=20)
    url = f"s3://{BUCKET}/out/sample.parquet"
    with pytest.raises(prism_stream.PrismError) as caught:
        prism_stream.sample(str(large), url, ratio=1.0, temp_dir=str(tmp_path))
    assert caught.value.exit_code == 8 and str(caught.value).startswith(url + ": "), caught.value
    proxy.disarm()
    assert _left(client) == ([], []), "the upload's parts were left in the store"
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("op,fault", [(op, f) for op, _, f in _grid([("head", 1), ("list", 1)], {("list", 1)})])
def test_a_failing_store_under_an_outputs_check_is_one_line_before_pass_one(s3env, large, tmp_path, monkeypatch,
                                                                           op, fault):
    """The output's existence check (before pass one) meets a store that fails: the run ends there, in bounded
    time, with the output's exit code (8, as its upload's), saying what failed, and nothing read or written."""
    from prism_stream.engines import pipeline

    proxy, client = s3env
    proxy.arm(op, fault)
    monkeypatch.setattr(pipeline, "solve", lambda *a, **kw: pytest.fail("the run went past the output's check"))
    url = f"s3://{BUCKET}/out/sample.parquet"
    before = _threads()
    with pytest.raises(prism_stream.PrismError) as caught:
        prism_stream.sample(str(large), url, ratio=1.0, temp_dir=str(tmp_path))
    assert proxy.faulted and time.monotonic() - proxy.tripped_at < WATCHDOG
    assert caught.value.exit_code == 8 and str(caught.value).startswith(url + ": "), caught.value
    assert "cannot check the output" in str(caught.value) or "could not be reached" in str(caught.value)
    assert "\n" not in str(caught.value)
    proxy.disarm()
    assert _left(client) == ([], [])
    assert os.listdir(tmp_path) == []
    _no_thread_left(before)


def test_a_request_failed_once_is_retried(s3env, large, tmp_path):
    proxy, client = s3env
    proxy.arm("upload_part", "status:503", 2, times=1)
    url = f"s3://{BUCKET}/out/sample.parquet"
    prism_stream.sample(str(large), url, ratio=1.0, temp_dir=str(tmp_path))
    assert proxy.faulted == ["upload_part"]
    assert _left(client) == (["out/sample.parquet"], [])


@pytest.mark.parametrize("fault", FAULTS)
def test_a_store_that_fails_in_pass_two_is_exit_10_and_leaves_nothing(s3env, tmp_path, monkeypatch, fault):
    """Reading twice, the input is read again in pass two: the store goes down after the solve (armed from
    inside the run), and the run still ends with exit 10 in bounded time, nothing written."""
    proxy, client = s3env
    _fail_after_solve(monkeypatch, proxy, fault)
    url = f"s3://{BUCKET}/in/autzen.las"
    before = _threads()
    with pytest.raises(StorageError) as caught:
        prism_stream.sample(url, str(tmp_path / "out.parquet"), ratio=0.1, reads="two", temp_dir=str(tmp_path))
    assert proxy.faulted and time.monotonic() - proxy.tripped_at < WATCHDOG
    assert str(caught.value).startswith(url + ": ") and caught.value.exit_code == 10
    assert "\n" not in str(caught.value)
    assert os.listdir(tmp_path) == []
    _no_thread_left(before)


def _run_until_fault(proxy, args: list, tmp_path, sig=None, env=None):
    """The command line's run against the proxy armed by the caller: (exit code, stderr, seconds from the
    fault to the process's end); ``sig`` is sent half a second after the fault. The watchdog is the
    subprocess's own timeout: a run that outlives its fault by WATCHDOG seconds fails the test."""
    proc = subprocess.Popen([*prism_stream_command(), *map(str, args), "--temp-dir", str(tmp_path)],
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env or user_env())
    try:
        deadline = time.monotonic() + 120
        while proxy.tripped_at is None and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        assert proxy.tripped_at is not None, "the run never reached the fault"
        if sig is not None:
            time.sleep(0.5)
            proc.send_signal(sig)
        _, err = proc.communicate(timeout=WATCHDOG)
        return proc.returncode, err, time.monotonic() - proxy.tripped_at
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.mark.parametrize("fault", ["stall", "refuse"])
def test_a_store_that_stops_mid_upload_ends_the_process(s3env, larger, tmp_path, fault):
    """The reported hang: the store stopped during a multipart upload, the error line came, and the process
    never exited (a thread or an event loop still waiting). Here as a user runs it, with no signal: exit 8,
    one line, the process gone within the watchdog, nothing left in the store or locally."""
    proxy, client = s3env
    proxy.arm("upload_part", fault, 2)
    env = user_env(**{remote.TIMEOUT_VAR: str(STALL), "AWS_MAX_ATTEMPTS": "1"})
    code, err, took = _run_until_fault(proxy, [larger, f"s3://{BUCKET}/out/sample.parquet", "--ratio", "1"],
                                       tmp_path, env=env)
    assert code == 8 and err.count("\n") == 1 and "cannot upload the output" in err, err
    assert took < WATCHDOG
    assert os.listdir(tmp_path) == []
    proxy.disarm()
    assert _left(client)[0] == []


@pytest.mark.parametrize("sig,code,word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")])
def test_a_signal_while_the_store_stalls_ends_the_run_within_seconds(s3env, larger, tmp_path, sig, code, word):
    """The store stops answering in the middle of the upload; SIGINT or SIGTERM ends the process at once (it
    waited, uninterruptible, in the SDK's retries of the abort), with its exit code and one line."""
    proxy, client = s3env
    proxy.arm("upload_part", "stall", 2)
    env = user_env(**{remote.TIMEOUT_VAR: "60"})  # the SDK alone would wait minutes
    started = time.monotonic()
    got, err, _ = _run_until_fault(proxy, [larger, f"s3://{BUCKET}/out/sample.parquet", "--ratio", "1"], tmp_path,
                                   sig=sig, env=env)
    signalled = proxy.tripped_at + 0.5
    assert time.monotonic() - max(signalled, started) < 10, "the run outlived the signal"  # 3 s for the abort
    assert got == code and err.count("\n") == 1 and word in err, err
    assert os.listdir(tmp_path) == []
    proxy.disarm()
    assert _left(client)[0] == []


def test_a_store_that_fails_under_dask_workers_is_exit_10_and_leaves_nothing(s3env, tmp_path):
    """On Dask the workers read the store: a store that goes down while they scan ends the run with the
    store's exit code and one line (raised on a worker, told on the driver), nothing beside the output."""
    distributed = pytest.importorskip("distributed")
    from prism_stream.engines import dask as dask_engine

    proxy, client = s3env
    url = f"s3://{BUCKET}/in/autzen.las"
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as c:
        for fault in ("refuse", "status:503"):
            proxy.arm("range", fault, 3)
            with pytest.raises(prism_stream.PrismError) as caught:
                dask_engine.sample(c, [url], str(tmp_path / "out"), ratio=0.1, unit_size=2_000)
            assert proxy.faulted and time.monotonic() - proxy.tripped_at < WATCHDOG
            assert type(caught.value) is StorageError and caught.value.exit_code == 10, (fault, caught.value)
            assert str(caught.value).startswith(url + ": ") and "\n" not in str(caught.value)
            assert os.listdir(tmp_path) == []
            proxy.disarm()


def test_a_folder_of_outputs_whose_store_goes_down_says_what_it_left(s3env, tmp_path):
    """Directory mode into the store: the second output's PUT fails and the store stays down, so the first
    output, uploaded already, cannot be removed: the line says which objects the store still holds (when the
    store still answers, they are removed, as test_remote checks)."""
    from conftest import random_colors, write_las

    proxy, client = s3env
    inputs = tmp_path / "in"
    inputs.mkdir()
    for i in range(3):
        write_las(inputs / f"t{i}.las", random_colors(3000, seed=i))
    work = tmp_path / "tmp"
    work.mkdir()
    proxy.arm("put", "refuse", 2)
    url = f"s3://{BUCKET}/out/dir/"
    with pytest.raises(prism_stream.PrismError) as caught:
        prism_stream.sample(str(inputs), url, ratio=0.5, temp_dir=str(work))
    proxy.disarm()
    assert caught.value.exit_code == 8 and "\n" not in str(caught.value), caught.value
    objects, _ = _left(client)
    assert objects == ["out/dir/t0.las"]
    assert f"could not be removed from the store: s3://{BUCKET}/out/dir/t0.las" in str(caught.value), caught.value
    assert os.listdir(work) == []


@pytest.mark.parametrize("server,op,nth,fault", [("ranged", "range", 2, "cut"), ("ranged", "range", 1, "status:503"),
                                                 ("ranged", "head", 1, "refuse"), ("plain", "read", 1, "cut"),
                                                 ("plain", "read", 1, "status:503")])
def test_an_http_server_failing_once_is_tried_again(http_faults, tmp_path, monkeypatch, server, op, nth, fault):
    """A transient fault (a body cut short, a 5xx, a refused connection) on one HTTP request is tried again,
    as S3's are: the run ends as an undisturbed one, with the same rows."""
    proxy = http_faults[server == "plain"]
    monkeypatch.setenv(remote.TIMEOUT_VAR, str(4 * STALL))
    url = f"{proxy.url}/data/scan.laz"
    outs = []
    for armed in (False, True):
        _forget_copies()
        if armed:
            proxy.arm(op, fault, nth, times=1)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", PrismWarning)
                out = tmp_path / f"{armed}.parquet"
                prism_stream.sample(url, str(out), ratio=0.3, temp_dir=str(tmp_path))
        finally:
            proxy.disarm()
        outs.append(pq.read_table(out))
    assert proxy.faulted == [op]
    assert outs[0].equals(outs[1]) and outs[0].num_rows > 0
    _forget_copies()
