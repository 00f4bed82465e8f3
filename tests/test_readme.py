"""Every `prism-stream` command of the README runs as written, on files named as it names them.

The README's shell blocks are read from the file itself, so an example that
changes is tested as changed. Each command runs in its own folder holding
what the examples name: ``big.laz`` (1.1 million points: the Autzen excerpt
tiled ten times, so that ``--count 1000000`` fits), ``cloud.laz`` (every
fourth point of it),
``tiles/`` (three LAZ tiles and three Parquet tiles; ``survey/`` is the same
folder) and ``jobs.csv``. The ``s3://bucket`` commands run against a local S3
server (moto's) holding the same tiles under ``bucket/tiles/``, reached through
the SDK's own variables, as a user's store is. The two commands that name a host
this machine does not have run against a local stand-in, the host's address
the only change: ``tcp://scheduler:8786`` is a Dask scheduler started here,
``https://example.org/`` that S3 server's plain-HTTP address (a public object
``scan.laz``, read in range requests as from any web server). Every command is
run; ``NOT_HERE`` would list one that cannot be, with where its engine is tested.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
from pathlib import Path

import laspy
import numpy as np
import pytest

from conftest import prism_stream_command, real_file, user_env

README = Path(__file__).resolve().parent.parent / "README.md"

NOT_HERE: dict = {}  # command -> where that engine is tested instead (none: every command runs)
SCHEDULER, WEB = "tcp://scheduler:8786", "https://example.org/"  # the hosts given a local stand-in


def readme_commands() -> list[str]:
    text = README.read_text()
    blocks = re.findall(r"```sh\n(.*?)```", text, re.S)
    out = []
    for block in blocks:
        for line in block.splitlines():
            line = re.split(r"\s{2,}#", line)[0].strip()  # the comment after a command
            if line.startswith("prism-stream "):
                out.append(line)
    return out


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("readme")
    autzen = laspy.read(str(real_file("pdal__autzen_trim.las")))
    big = laspy.LasData(autzen.header)
    parts = []
    for i in range(10):
        p = autzen.points.copy()
        p.X = p.X + i * 200_000  # side by side, 2,000 ft apart
        parts.append(p.array)
    big.points = laspy.PackedPointRecord(np.concatenate(parts), autzen.header.point_format)
    big.write(str(folder / "big.laz"))
    small = laspy.LasData(autzen.header)  # cloud.laz: every fourth point (eval's metrics grow with the points)
    small.points = autzen.points[::4].copy()
    small.write(str(folder / "cloud.laz"))
    tiles = folder / "tiles"
    tiles.mkdir()
    n = len(autzen.points)
    for i in range(3):
        piece = laspy.LasData(autzen.header)
        piece.points = autzen.points[i * n // 3:(i + 1) * n // 3].copy()
        piece.write(str(tiles / f"tile_{i}.laz"))
    import prism_stream

    for i in range(3):
        prism_stream.sample(str(tiles / f"tile_{i}.laz"), str(tiles / f"tile_{i}.parquet"), ratio=1.0)
    (folder / "jobs.csv").write_text("job_id,inputs,ratio,output\none,cloud.laz,0.01,one.parquet\n"
                                     "two,tiles/*.laz,0.05,two.laz\n")
    return folder


def test_the_readme_has_its_commands():
    commands = readme_commands()
    assert len(commands) >= 15
    assert set(NOT_HERE) <= set(commands), "NOT_HERE names a command the README no longer has"
    assert any(SCHEDULER in c for c in commands) and any(WEB in c for c in commands)


@pytest.mark.parametrize("command", [c for c in readme_commands() if c not in NOT_HERE])
def test_readme_command_runs_as_written(command, files, tmp_path, request):
    for name in ("big.laz", "cloud.laz", "tiles", "jobs.csv"):
        os.symlink(files / name, tmp_path / name)
    os.symlink(files / "tiles", tmp_path / "survey")
    env = user_env(MPLBACKEND="Agg")  # as a user runs it: big.laz streams, the smaller files are held in memory
    if "s3://bucket" in command or WEB in command:
        env.update(request.getfixturevalue("bucket"))
        command = command.replace(WEB, env["AWS_ENDPOINT_URL"] + "/bucket/")
    if SCHEDULER in command:
        command = command.replace(SCHEDULER, request.getfixturevalue("scheduler"))
    args = shlex.split(command)[1:]
    run = subprocess.run([*prism_stream_command(), *args], cwd=tmp_path, capture_output=True, text=True, env=env,
                         timeout=600)
    assert run.returncode == 0, f"{command}\n{run.stderr[-2000:]}"
    assert "Traceback" not in run.stderr
    if "--dask " in command:
        # what the README says of it: out.parquet is a folder of parts, read as one by DuckDB and pyarrow
        import duckdb
        import pyarrow.dataset as ds

        out = tmp_path / "out.parquet"
        assert out.is_dir() and len(list(out.glob("*.parquet"))) >= 1
        rows = duckdb.sql(f"SELECT count(*) FROM read_parquet('{out}/*.parquet')").fetchall()[0][0]
        assert rows == ds.dataset(str(out)).count_rows() == 1_100  # 1% of the three tiles' 110,000 points
    if "/bucket/scan.laz" in command:  # the web server's file, read in ranges: 1% of its points
        import pyarrow.parquet as pq

        points = laspy.open(files / "cloud.laz").header.point_count
        assert pq.read_metadata(tmp_path / "out.parquet").num_rows == round(0.01 * points)
    if "s3://bucket" in command:  # what it wrote is in the store (or here), with 1% of the tiles' points
        import boto3
        import pyarrow.parquet as pq

        bucket = request.getfixturevalue("bucket")
        client = boto3.client("s3", endpoint_url=bucket["AWS_ENDPOINT_URL"], region_name="us-east-1",
                              aws_access_key_id="testing", aws_secret_access_key="testing")
        if args[1] == "out.las":
            assert laspy.read(tmp_path / "out.las").header.point_count == 1_100
        elif args[1].endswith(".parquet"):
            client.download_file("bucket", "out.parquet", str(tmp_path / "got.parquet"))
            assert pq.read_metadata(tmp_path / "got.parquet").num_rows == 1_100
        else:  # one object per tile
            keys = [o["Key"] for o in client.list_objects_v2(Bucket="bucket", Prefix="sampled/")["Contents"]]
            assert keys == [f"sampled/tile_{i}.laz" for i in range(3)]


@pytest.fixture
def bucket(files):
    """A local S3 server holding the README's tiles in ``bucket/tiles/`` (a new one for each command, so that
    an output of one is not the input or the existing output of another): the store's variables."""
    import boto3
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        env = {"AWS_ENDPOINT_URL": f"http://{host}:{port}", "AWS_ACCESS_KEY_ID": "testing",
               "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1",
               "AWS_EC2_METADATA_DISABLED": "true", "AWS_SHARED_CREDENTIALS_FILE": os.devnull,
               "AWS_CONFIG_FILE": os.devnull}
        client = boto3.client("s3", endpoint_url=env["AWS_ENDPOINT_URL"], region_name="us-east-1",
                              aws_access_key_id="testing", aws_secret_access_key="testing")
        client.create_bucket(Bucket="bucket")
        for tile in sorted((files / "tiles").glob("*.laz")):
            client.upload_file(str(tile), "bucket", f"tiles/{tile.name}")
        client.upload_file(str(files / "cloud.laz"), "bucket", "scan.laz", ExtraArgs={"ACL": "public-read"})
        yield env
    finally:
        server.stop()


@pytest.fixture
def scheduler():
    """A Dask scheduler with one worker (threads of this process), for the README's tcp://scheduler:8786."""
    import distributed

    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, protocol="tcp",
                                  dashboard_address=None) as cluster:  # reached from the command's own process
        yield cluster.scheduler_address


def test_every_exit_code_is_in_the_readme_table():
    """Each error class's exit code has a row in the README's table (a new one, like 11, cannot go unsaid)."""
    import importlib
    import pkgutil

    import prism_stream
    import prism_stream.errors as errors

    text = README.read_text()
    table = text[text.index("### Exit codes"):]
    rows = set(re.findall(r"^\| (\d+) \|", table, re.M))
    for module in pkgutil.walk_packages(prism_stream.__path__, "prism_stream."):  # error classes outside errors.py
        importlib.import_module(module.name)  # (the Dask engine's ClusterError) are PrismError's subclasses too
    found, seen = [errors.PrismError], set()
    while found:
        c = found.pop()
        seen.add(c)
        found.extend(c.__subclasses__())
    codes = {str(c.exit_code) for c in seen}
    assert "9" in codes
    assert codes - {"1"} <= rows, codes - rows  # 1 is the base class's (batch's row says what 1 means)
