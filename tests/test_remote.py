"""Object storage: inputs and outputs at s3:// URLs give the local run's rows, an output object appears
whole or not at all, and a store's failure is one line.

An S3 server (moto's, in this process, on localhost) stands in for the store; the credentials and the
endpoint reach prism-stream only through the environment, as they would in production.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import boto3
import laspy
import pyarrow.parquet as pq
import pytest
from moto.server import ThreadedMotoServer

import prism_stream
from prism_stream.errors import Interrupted, OutputError
from prism_stream.run import remote

from conftest import edge_file, prism_stream_command, real_file, user_env

AUTZEN = real_file("pdal__autzen_trim.las")
LION = real_file("potree__lion_takanawa.copc.laz")
PDAL_PARQUET = edge_file("pdal__1.2-with-color.parquet")
BUCKET = "scans"


@pytest.fixture(scope="module")
def server():
    s = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    s.start()
    host, port = s.get_host_and_port()
    yield f"http://{host}:{port}"
    s.stop()


def store_environment(endpoint: str) -> dict:
    """What a user sets: credentials and the endpoint, in the SDK's own variables (never on the command line)."""
    return {"AWS_ENDPOINT_URL": endpoint, "AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
            "AWS_DEFAULT_REGION": "us-east-1", "AWS_EC2_METADATA_DISABLED": "true",  # never ask a metadata server
            "AWS_SHARED_CREDENTIALS_FILE": os.devnull, "AWS_CONFIG_FILE": os.devnull}


@pytest.fixture
def env(server, monkeypatch):
    for name, value in store_environment(server).items():
        monkeypatch.setenv(name, value)
    for name in ("AWS_PROFILE", "AWS_SESSION_TOKEN", "AWS_ENDPOINT_URL_S3"):
        monkeypatch.delenv(name, raising=False)
    return server


@pytest.fixture(scope="module")
def tiles(tmp_path_factory) -> Path:
    """Autzen cut into three LAZ tiles, named so that sorted order is cut order."""
    folder = tmp_path_factory.mktemp("tiles")
    las = laspy.read(AUTZEN)
    n = len(las.points)
    for i in range(3):
        piece = laspy.LasData(las.header)
        piece.points = las.points[n * i // 3:n * (i + 1) // 3].copy()
        piece.write(folder / f"tile_{i}.laz")
    return folder


@pytest.fixture
def s3(env, tiles):
    """A fresh bucket holding the tiles under tiles/, autzen and a GeoParquet file under mixed/."""
    client = boto3.client("s3", endpoint_url=env, region_name="us-east-1")
    for page in client.get_paginator("list_objects_v2").paginate(Bucket=BUCKET) if _exists(client) else []:
        for obj in page.get("Contents", []):
            client.delete_object(Bucket=BUCKET, Key=obj["Key"])
    if not _exists(client):
        client.create_bucket(Bucket=BUCKET)
    for p in sorted(tiles.iterdir()):
        client.upload_file(str(p), BUCKET, f"tiles/{p.name}")
    client.upload_file(str(AUTZEN), BUCKET, "mixed/b/autzen.las")
    client.upload_file(str(tiles / "tile_0.laz"), BUCKET, "mixed/a/tile_0.laz")
    client.upload_file(str(tiles / "tile_1.laz"), BUCKET, "mixed/.hidden/tile_1.laz")
    client.upload_file(str(PDAL_PARQUET), BUCKET, "parquet/cloud.parquet")
    client.upload_file(str(tiles / "tile_2.laz"), BUCKET, "public/tile_2.laz", ExtraArgs={"ACL": "public-read"})
    return client


def _exists(client) -> bool:
    return any(b["Name"] == BUCKET for b in client.list_buckets().get("Buckets", []))


def keys(client, prefix: str = "") -> list[str]:
    return [o["Key"] for o in client.list_objects_v2(Bucket=BUCKET, Prefix=prefix).get("Contents", [])]


def fetch(client, key: str, folder: Path) -> Path:
    path = folder / ("fetched-" + key.replace("/", "_"))
    client.download_file(BUCKET, key, str(path))
    return path


def cli(*args, cwd) -> subprocess.CompletedProcess:
    """The command in a user's environment (the store's variables included): small tiles held in memory; the
    streaming path reads the store in this process, in the tests that call prism_stream.sample."""
    done = subprocess.run([*prism_stream_command(), *map(str, args)], cwd=cwd, capture_output=True, text=True,
                          timeout=300, env=user_env())
    assert "Traceback" not in done.stderr + done.stdout, done.stderr
    return done


def without_paths(provenance: dict) -> dict:
    """Provenance less the file names (a URL in one run, a local path in the other), the command line and
    the time."""
    out = {k: v for k, v in provenance.items() if k not in ("inputs", "command", "created")}
    out["sources"] = [{k: v for k, v in s.items() if k != "path"} for s in provenance["sources"]]
    return out


def test_glob_in_the_store_to_an_object_is_the_local_run(s3, tiles, tmp_path):
    url = f"s3://{BUCKET}/out.parquet"
    done = cli(f"s3://{BUCKET}/tiles/*.laz", url, "--ratio", "0.01", "--json", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["inputs"] == [f"s3://{BUCKET}/tiles/tile_{i}.laz" for i in range(3)]  # sorted, as local globs
    assert summary["output"] == url
    local = tmp_path / "local.parquet"
    expected = prism_stream.sample(str(tiles / "*.laz"), str(local), ratio=0.01)
    got = pq.read_table(fetch(s3, "out.parquet", tmp_path))
    assert got.equals(pq.read_table(local))
    assert got.num_rows == expected.kept == summary["kept"] == 1_100
    meta = json.loads(got.schema.metadata[b"prism_stream"])
    assert without_paths(meta) == without_paths(json.loads(pq.read_schema(local).metadata[b"prism_stream"]))
    assert meta["inputs"] == summary["inputs"] and meta["command"][1:3] == [f"s3://{BUCKET}/tiles/*.laz", url]
    assert keys(s3) == ["mixed/.hidden/tile_1.laz", "mixed/a/tile_0.laz", "mixed/b/autzen.las", "out.parquet",
                        "parquet/cloud.parquet", "public/tile_2.laz", "tiles/tile_0.laz", "tiles/tile_1.laz",
                        "tiles/tile_2.laz"]
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]  # the local staging is gone

    again = cli(f"s3://{BUCKET}/tiles/*.laz", url, "--ratio", "0.01", cwd=tmp_path)
    assert again.returncode == 7 and again.stderr.count("\n") == 1 and "already exists" in again.stderr
    assert cli(f"s3://{BUCKET}/tiles/*.laz", url, "--ratio", "0.02", "--overwrite", "-q", cwd=tmp_path).returncode == 0
    assert pq.read_metadata(fetch(s3, "out.parquet", tmp_path)).num_rows == 2_200


def test_remote_las_output_and_uncompressed_input(s3, tmp_path):
    """An uncompressed LAS in the store: pass one reads its colors in byte ranges (locally: a memory map)."""
    prism_stream.sample(f"s3://{BUCKET}/mixed/b/autzen.las", f"s3://{BUCKET}/sample.laz", ratio=0.05, seed=4,
                        reads="two")
    prism_stream.sample(str(AUTZEN), str(tmp_path / "local.laz"), ratio=0.05, seed=4, reads="two")
    got = laspy.read(fetch(s3, "sample.laz", tmp_path))
    assert got.points.array.tobytes() == laspy.read(tmp_path / "local.laz").points.array.tobytes()


def test_remote_copc_output(s3, tmp_path):
    """A COPC output in the store: built in the local staging, uploaded whole at the end, and the same
    points as the local run's COPC."""
    url = f"s3://{BUCKET}/preview.copc.laz"
    done = cli(f"s3://{BUCKET}/mixed/b/autzen.las", url, "--ratio", "0.05", "-q", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]  # the local staging is gone
    prism_stream.sample(str(AUTZEN), str(tmp_path / "local.copc.laz"), ratio=0.05)
    with laspy.CopcReader.open(str(fetch(s3, "preview.copc.laz", tmp_path))) as got, \
            laspy.CopcReader.open(str(tmp_path / "local.copc.laz")) as want:
        assert got.query().array.tobytes() == want.query().array.tobytes()


def test_https_input_is_read_in_ranges(s3, env, tiles, tmp_path):
    """A public object over plain HTTP (fsspec's http filesystem, range requests), no store library."""
    url = f"{env}/{BUCKET}/public/tile_2.laz"
    summary = prism_stream.sample(url, str(tmp_path / "remote.las"), ratio=0.1)
    prism_stream.sample(str(tiles / "tile_2.laz"), str(tmp_path / "local.las"), ratio=0.1)
    a, b = laspy.read(tmp_path / "remote.las"), laspy.read(tmp_path / "local.las")
    assert a.points.array.tobytes() == b.points.array.tobytes()
    assert summary.inputs == [url] and summary.kept == len(a.points) > 0


def test_remote_parquet_input(s3, tmp_path):
    url = f"s3://{BUCKET}/parquet/cloud.parquet"
    summary = prism_stream.sample(url, str(tmp_path / "remote.parquet"), ratio=0.2)
    prism_stream.sample(str(PDAL_PARQUET), str(tmp_path / "local.parquet"), ratio=0.2)
    assert pq.read_table(tmp_path / "remote.parquet").equals(pq.read_table(tmp_path / "local.parquet"))
    assert summary.inputs == [url] and summary.kept > 0


def test_remote_folder_is_walked_in_sorted_order_skipping_hidden_folders(s3, tiles, tmp_path):
    summary = prism_stream.sample(f"s3://{BUCKET}/mixed", str(tmp_path / "remote.las"), ratio=0.03)
    assert summary.inputs == [f"s3://{BUCKET}/mixed/a/tile_0.laz", f"s3://{BUCKET}/mixed/b/autzen.las"]
    prism_stream.sample([str(tiles / "tile_0.laz"), str(AUTZEN)], str(tmp_path / "local.las"), ratio=0.03)
    a, b = laspy.read(tmp_path / "remote.las"), laspy.read(tmp_path / "local.las")
    assert a.points.array.tobytes() == b.points.array.tobytes()
    # the same tree, listed one level deeper by a recursive glob: the same order
    assert prism_stream.plan(f"s3://{BUCKET}/mixed/*/*.la[sz]", ratio=0.03).inputs == summary.inputs


def test_dask_workers_read_the_store(s3, tiles, tmp_path):
    """`--dask local:1`: the worker, a process of its own, opens the URLs itself (no folder shared with the tiles)."""
    out = tmp_path / "out"
    done = cli(f"s3://{BUCKET}/tiles/*.laz", out, "--ratio", "0.02", "--dask", "local:1", "--json", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["inputs"] == [f"s3://{BUCKET}/tiles/tile_{i}.laz" for i in range(3)]
    from prism_stream.engines.dask import read_dataset

    expected = prism_stream.sample(str(tiles / "*.laz"), str(tmp_path / "local.parquet"), ratio=0.02)
    got = read_dataset(str(out))
    assert got.equals(pq.read_table(tmp_path / "local.parquet"))
    assert got.num_rows == expected.kept
    refused = cli(f"s3://{BUCKET}/tiles/*.laz", f"s3://{BUCKET}/dataset", "--ratio", "0.02", "--dask", "local:1",
                  cwd=tmp_path)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr


def test_remote_folder_to_remote_folder_is_directory_mode(s3, tiles, tmp_path, monkeypatch):
    """One output object per input tile; if one upload fails, the objects already up are deleted."""
    summary = prism_stream.sample(f"s3://{BUCKET}/tiles/", f"s3://{BUCKET}/out/", ratio=0.02)
    prism_stream.sample(str(tiles), str(tmp_path / "local") + "/", ratio=0.02)
    names = [f"out/tile_{i}.laz" for i in range(3)]
    assert keys(s3, "out/") == names and summary.outputs == [f"s3://{BUCKET}/{n}" for n in names]
    for i, name in enumerate(names):
        got = laspy.read(fetch(s3, name, tmp_path)).points.array.tobytes()
        assert got == laspy.read(tmp_path / "local" / f"tile_{i}.laz").points.array.tobytes()

    real, calls = remote.upload, []

    def third_fails(local, url, overwrite):
        calls.append(url)
        if len(calls) == 3:
            raise OutputError("cannot upload the output: injected", url)
        real(local, url, overwrite)

    monkeypatch.setattr(remote, "upload", third_fails)
    with pytest.raises(OutputError, match="injected"):
        prism_stream.sample(f"s3://{BUCKET}/tiles/", f"s3://{BUCKET}/again/", ratio=0.02, output_format="parquet")
    assert len(calls) == 3 and keys(s3, "again/") == []


class FailingPart:
    """Stands in for S3File._upload_chunk: the first part goes up, the next one fails (or is interrupted)."""

    def __init__(self, real, exc):
        self.real, self.exc, self.calls, self.pending = real, exc, 0, None

    def __call__(self, file, final=False):
        self.calls += 1
        if self.calls > 1:
            self.pending = boto3.client("s3").list_multipart_uploads(Bucket=BUCKET).get("Uploads", [])
            raise self.exc
        return self.real(file, final)


@pytest.mark.parametrize("exc, error", [(ConnectionResetError("connection reset by peer"), OutputError),
                                        (KeyboardInterrupt(), Interrupted)])
def test_an_upload_failing_half_way_leaves_no_object(s3, tmp_path, monkeypatch, exc, error):
    import s3fs

    failing = FailingPart(s3fs.core.S3File._upload_chunk, exc)
    monkeypatch.setattr(s3fs.core.S3File, "_upload_chunk", lambda self, final=False: failing(self, final))
    monkeypatch.setattr(remote, "UPLOAD_BLOCK", 5 << 20)  # S3's smallest part: a 12 MB output is three parts
    with pytest.raises(error) as info:
        prism_stream.sample(str(LION), f"s3://{BUCKET}/lion.las", ratio=1.0)
    assert "\n" not in str(info.value) and "lion.las" in str(info.value)
    assert failing.calls == 2 and len(failing.pending) == 1  # a multipart upload was under way, one part up
    assert keys(s3, "lion") == []
    assert s3.list_multipart_uploads(Bucket=BUCKET).get("Uploads", []) == []  # aborted: nothing left to pay for
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]


def test_a_large_upload_is_one_multipart_object(s3, tmp_path, monkeypatch):
    monkeypatch.setattr(remote, "UPLOAD_BLOCK", 5 << 20)
    with pytest.warns(prism_stream.PrismWarning, match=f"^s3://{BUCKET}/lion.las: COPC VLRs"):  # named as published
        summary = prism_stream.sample(str(LION), f"s3://{BUCKET}/lion.las", ratio=1.0)
    head = s3.head_object(Bucket=BUCKET, Key="lion.las")
    assert head["ContentLength"] > 10 << 20 and "-" in head["ETag"]  # a multipart upload's ETag
    assert len(laspy.read(fetch(s3, "lion.las", tmp_path)).points) == summary.kept == 341_989


@pytest.mark.parametrize("what, code, message", [
    ("s3://scans/tiles/nope.laz", 3, "no such"),
    ("s3://no-such-bucket/tiles/a.laz", 3, "bucket"),
    ("s3://scans/nothing/*.laz", 3, "matches no file"),
    ("s3://scans/parquet/cloud.ply", 3, "no such"),
])
def test_a_missing_object_is_one_line(s3, tmp_path, what, code, message):
    done = cli(what, tmp_path / "out.parquet", "--ratio", "0.1", cwd=tmp_path)
    assert done.returncode == code, done.stderr
    assert done.stderr.count("\n") == 1 and done.stderr.startswith("prism-stream: error: "), done.stderr
    assert what in done.stderr and message in done.stderr.lower()
    assert os.listdir(tmp_path) == []


def test_no_credentials_and_no_store_are_one_line(s3, tmp_path, monkeypatch):
    monkeypatch.delenv("AWS_ACCESS_KEY_ID")
    monkeypatch.delenv("AWS_SECRET_ACCESS_KEY")
    done = cli(f"s3://{BUCKET}/tiles/tile_0.laz", tmp_path / "out.parquet", "--ratio", "0.1", cwd=tmp_path)
    assert done.returncode == 10 and done.stderr.count("\n") == 1, done.stderr
    assert "credentials" in done.stderr
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    monkeypatch.setenv("AWS_ENDPOINT_URL", "http://127.0.0.1:9")  # nothing listens on the discard port
    monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")
    done = cli(f"s3://{BUCKET}/tiles/tile_0.laz", tmp_path / "out.parquet", "--ratio", "0.1", cwd=tmp_path)
    assert done.returncode == 10 and done.stderr.count("\n") == 1, done.stderr
    assert f"s3://{BUCKET}/tiles/tile_0.laz: the store failed" in done.stderr
    assert os.listdir(tmp_path) == []


def test_what_is_not_read_or_written_remotely_is_refused_by_name(s3, env, tmp_path):
    s3.put_object(Bucket=BUCKET, Key="cloud.ply", Body=b"ply\n")
    done = cli(f"s3://{BUCKET}/cloud.ply", tmp_path / "out.parquet", "--ratio", "0.1", cwd=tmp_path)
    assert done.returncode == 4 and done.stderr.count("\n") == 1 and "local paths only" in done.stderr
    done = cli(f"s3://{BUCKET}/tiles/tile_0.laz", f"{env}/{BUCKET}/out.parquet", "--ratio", "0.1", cwd=tmp_path)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "read-only" in done.stderr
    assert os.listdir(tmp_path) == []


def test_help_names_urls_and_loads_no_store_library(tmp_path):
    done = cli("sample", "--help", cwd=tmp_path)
    assert "s3://" in done.stdout and "AWS_ENDPOINT_URL" in done.stdout
    probe = ("import sys; from prism_stream_cli.main import run\n"
             "try:\n    run(['sample', '--help'])\nexcept SystemExit:\n    pass\n"
             "print(sorted(m for m in sys.modules if m.split('.')[0] in ('fsspec', 's3fs', 'botocore')))")
    loaded = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path)
    assert loaded.stdout.strip().splitlines()[-1] == "[]", loaded.stdout + loaded.stderr


def test_a_missing_object_or_bucket_is_told_by_the_stores_code_not_its_words(s3, tmp_path):
    """A missing key whose name holds "bucket" and "credentials" is a missing object (3); a missing bucket is a
    missing bucket (3); writing into a bucket whose name holds "bucket" works (the README's own s3://bucket
    failed as 'no such bucket', exit 8, before: issue 32)."""
    done = cli(f"s3://{BUCKET}/no-bucket-credentials.laz", tmp_path / "o.parquet", "--ratio", "0.1", cwd=tmp_path)
    assert done.returncode == 3 and "no such bucket" not in done.stderr, done.stderr
    done = cli("s3://no-such-bucket-here/tile.laz", tmp_path / "o.parquet", "--ratio", "0.1", cwd=tmp_path)
    assert done.returncode == 3 and "no such bucket" in done.stderr, done.stderr
    client = boto3.client("s3", endpoint_url=os.environ["AWS_ENDPOINT_URL"], region_name="us-east-1")
    client.create_bucket(Bucket="my-bucket")
    done = cli(f"s3://{BUCKET}/tiles/tile_0.laz", "s3://my-bucket/out.parquet", "--ratio", "0.1", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert [o["Key"] for o in client.list_objects_v2(Bucket="my-bucket")["Contents"]] == ["out.parquet"]
