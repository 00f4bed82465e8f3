"""Stores as they are and as they fail (issue 32): HTTP servers without range requests, hosts that cannot be
reached, and an S3 store behind a proxy that refuses, stalls, cuts a connection or answers an error status at
a chosen request (``storeproxy.py``). Every case ends with the documented exit code and one line, leaves
nothing in the store or locally, and no run outlives its fault by more than 30 s (a watchdog: the
subprocess's own timeout, not a sleep).
"""

from __future__ import annotations

import os
import signal
import subprocess
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


@pytest.fixture(scope="module")
def large(tmp_path_factory):
    """A local input whose whole sample (12 MB of Parquet) is a multipart upload of three 5 MiB parts."""
    import numpy as np
    import pyarrow as pa

    path = tmp_path_factory.mktemp("large") / "large.parquet"
    rng = np.random.default_rng(3)
    n = 400_000
    pq.write_table(pa.table({"x": rng.random(n), "y": rng.random(n), "z": rng.random(n),
                             **{c: rng.integers(0, 65536, n).astype(np.uint16) for c in ("red", "green", "blue")}}),
                   path, compression="none")
    return path


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
    monkeypatch.setattr(remote, "UPLOAD_BLOCK", 5 << 20)  # S3's smallest part: a 12 MB output is 3 parts
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


# (operation, fault, nth, times): the store goes down at the nth request of that operation (times None), or
# fails that many requests of it in a row
READ_FAULTS = [("head", "refuse", 1, None), ("list", "status:503", 1, None), ("range", "stall", 2, None),
               ("range", "cut", 1, None)]  # "list": the input is a glob
WRITE_FAULTS = [("create_multipart", "status:500", 1, None), ("upload_part", "refuse", 2, None),
                ("upload_part", "status:503", 2, 20), ("complete_multipart", "cut", 1, None)]


@pytest.mark.parametrize("op,fault,nth,times", READ_FAULTS)
def test_a_failing_store_under_an_input_is_exit_10_in_bounded_time(s3env, tmp_path, op, fault, nth, times):
    proxy, client = s3env
    proxy.arm(op, fault, nth, times)
    out = tmp_path / "out.parquet"
    url = f"s3://{BUCKET}/in/{'*' if op == 'list' else 'autzen'}.las"
    with pytest.raises(prism_stream.PrismError) as caught:
        prism_stream.sample(url, str(out), ratio=0.1, temp_dir=str(tmp_path))
    ended = time.monotonic()
    assert proxy.faulted and ended - proxy.tripped_at < WATCHDOG
    assert type(caught.value) is StorageError and caught.value.exit_code == 10, caught.value
    assert str(caught.value).startswith(url + ": ") and "\n" not in str(caught.value)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("op,fault,nth,times", WRITE_FAULTS)
def test_a_failing_store_under_an_output_is_exit_8_and_leaves_nothing(s3env, large, tmp_path, op, fault, nth, times):
    """Each phase of a multipart upload: the run ends with exit 8 in bounded time and no object appears; a
    store that still answers (one part refused 20 times: more than the SDK tries) has the upload aborted, so
    no part is left to pay for."""
    proxy, client = s3env
    proxy.arm(op, fault, nth, times)
    url = f"s3://{BUCKET}/out/sample.parquet"
    with pytest.raises(prism_stream.PrismError) as caught:
        prism_stream.sample(str(large), url, ratio=1.0, temp_dir=str(tmp_path))
    ended = time.monotonic()
    assert proxy.faulted and ended - proxy.tripped_at < WATCHDOG, (op, fault)
    assert caught.value.exit_code == 8 and str(caught.value).startswith(url + ": "), caught.value
    proxy.disarm()
    objects, uploads = _left(client)
    assert objects == []
    if times is not None:
        assert uploads == [], "the upload's parts were left in the store"
    assert os.listdir(tmp_path) == []


def test_a_request_failed_once_is_retried(s3env, large, tmp_path):
    proxy, client = s3env
    proxy.arm("upload_part", "status:503", 2, times=1)
    url = f"s3://{BUCKET}/out/sample.parquet"
    prism_stream.sample(str(large), url, ratio=1.0, temp_dir=str(tmp_path))
    assert proxy.faulted == ["upload_part"]
    assert _left(client) == (["out/sample.parquet"], [])


def test_an_interrupt_while_the_store_stalls_ends_the_run_within_seconds(s3env, large, tmp_path):
    """The store stops answering in the middle of the upload; SIGINT ends the process at once (it waited,
    uninterruptible, in the SDK's retries of the abort), with exit 130 and one line."""
    proxy, client = s3env
    proxy.arm("upload_part", "stall", 2)
    env = user_env(**{remote.TIMEOUT_VAR: "60"})  # the SDK alone would wait minutes
    proc = subprocess.Popen([*prism_stream_command(), str(large), f"s3://{BUCKET}/out/sample.parquet",
                             "--ratio", "1", "--temp-dir", str(tmp_path)], stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 120
        while proxy.tripped_at is None and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        assert proxy.tripped_at is not None, "the run never reached its second part"
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        signalled = time.monotonic()
        _, err = proc.communicate(timeout=WATCHDOG)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert time.monotonic() - signalled < 10, "the run outlived the interrupt"  # 3 s for the abort, then out
    assert proc.returncode == 130 and err.count("\n") == 1 and "interrupted" in err, err
    assert os.listdir(tmp_path) == []
    proxy.disarm()
    assert _left(client)[0] == []


def test_a_store_that_fails_in_pass_two_is_exit_10_and_leaves_nothing(s3env, tmp_path, monkeypatch):
    """Reading twice, the input is read again in pass two: the store goes down after the solve (armed from
    inside the run), and the run still ends with exit 10 in bounded time, nothing written."""
    from prism_stream.engines import pipeline

    proxy, client = s3env
    real = pipeline.solve

    def solve_then_fail(*a, **kw):
        proxy.arm("range", "refuse")
        return real(*a, **kw)

    monkeypatch.setattr(pipeline, "solve", solve_then_fail)
    url = f"s3://{BUCKET}/in/autzen.las"
    with pytest.raises(StorageError) as caught:
        prism_stream.sample(url, str(tmp_path / "out.parquet"), ratio=0.1, reads="two", temp_dir=str(tmp_path))
    assert proxy.faulted and time.monotonic() - proxy.tripped_at < WATCHDOG
    assert str(caught.value).startswith(url + ": ") and caught.value.exit_code == 10
    assert os.listdir(tmp_path) == []
