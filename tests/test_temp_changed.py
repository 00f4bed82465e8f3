"""Temporary data changed under a run (issue 32): the spill or the key cache truncated, emptied, replaced
with garbage or removed with its folder, by another process, in pass one, between the passes or in pass
two. Each ends in one line naming the temporary folder (exit 11, README), no output and nothing left; never
an internal error, a failed assertion, or an output built from garbage.
"""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

import prism_stream
from prism_stream.engines import pipeline
from prism_stream.errors import TempDataChanged
from prism_stream.run import spill as spill_mod
from prism_stream.run import staging

from conftest import random_colors, write_las


@pytest.fixture(scope="module")
def cloud(tmp_path_factory):
    path = tmp_path_factory.mktemp("changed") / "cloud.las"
    write_las(path, random_colors(200_000, seed=5, palette=4000), point_format=3)
    return path


def _work(temp) -> str:
    [work] = [os.path.join(temp, n) for n in os.listdir(temp) if n.startswith(staging.WORK_PREFIX)]
    return work


def truncate(work):
    with open(os.path.join(work, "spill.keys"), "r+b") as f:
        f.truncate(os.path.getsize(f.name) // 2)


def empty(work):
    open(os.path.join(work, "spill.ids"), "wb").close()


def _replace_with_garbage(path):
    data = np.random.default_rng(1).bytes(os.path.getsize(path))
    os.unlink(path)  # a new file of the same size, as an editor or a copy would leave
    with open(path, "wb") as f:
        f.write(data)


def garbage(work):
    _replace_with_garbage(os.path.join(work, "spill.frames"))


def remove_folder(work):
    shutil.rmtree(work)


def truncate_cache(work):
    with open(_cache(work), "r+b") as f:
        f.truncate(8)


DAMAGES = {"truncated": truncate, "emptied": empty, "garbage": garbage, "removed": remove_folder}


def _hook(monkeypatch, phase, damage, temp):
    """Damage the run's files at ``phase``: in pass one (its third spilled chunk), after it (the solve), or in
    pass two (before the output is written)."""
    def later(real, at=1):
        calls = [0]

        def wrapped(*a, **kw):
            calls[0] += 1
            if calls[0] == at:
                damage(_work(temp))
            return real(*a, **kw)
        return wrapped

    if phase == "pass one":
        monkeypatch.setattr(spill_mod.Spill, "add", later(spill_mod.Spill.add, at=3))
    elif phase == "between":
        monkeypatch.setattr(pipeline, "solve", later(pipeline.solve))
    else:
        monkeypatch.setattr(pipeline, "write_outputs", later(pipeline.write_outputs))


# a frame file replaced in pass one is found at the next write (below): pass one reads no frame back
CASES = [(phase, damage) for phase in ("pass one", "between", "pass two") for damage in sorted(DAMAGES)
         if (phase, damage) != ("pass one", "garbage")]


@pytest.mark.parametrize("phase,damage", CASES)
def test_a_changed_spill_is_one_line_and_leaves_nothing(cloud, tmp_path, monkeypatch, phase, damage):
    temp = tmp_path / "tmp"
    temp.mkdir()
    _hook(monkeypatch, phase, DAMAGES[damage], temp)
    out = tmp_path / "out.parquet"
    with pytest.raises(TempDataChanged) as caught:
        prism_stream.sample(str(cloud), str(out), ratio=0.05, chunk_size=20_000, temp_dir=str(temp))
    message = str(caught.value)
    assert caught.value.exit_code == 11 and message.startswith(f"{temp}: temporary data was changed"), message
    assert "\n" not in message
    assert not out.exists() and os.listdir(temp) == [] and os.listdir(tmp_path) == ["tmp"]


def test_a_spill_file_replaced_in_pass_one_is_seen_at_the_next_write(cloud, tmp_path, monkeypatch):
    temp = tmp_path / "tmp"
    temp.mkdir()
    _hook(monkeypatch, "pass one", garbage, temp)
    with pytest.raises(TempDataChanged, match="spill.frames was replaced"):
        prism_stream.sample(str(cloud), str(tmp_path / "out.parquet"), ratio=0.05, chunk_size=20_000,
                            temp_dir=str(temp))


def _cache(work) -> str:
    [name] = [n for n in os.listdir(work) if n not in ("spill.keys", "spill.ids", "spill.frames")]
    return os.path.join(work, name)


def empty_cache(work):
    open(_cache(work), "wb").close()


def garbage_cache(work):
    _replace_with_garbage(_cache(work))


CACHE_DAMAGES = {"truncated": truncate_cache, "emptied": empty_cache, "garbage": garbage_cache,
                 "removed": remove_folder}


@pytest.mark.parametrize("damage", sorted(CACHE_DAMAGES))
@pytest.mark.parametrize("phase", ["pass one", "between", "pass two"])
def test_a_changed_key_cache_is_one_line(cloud, tmp_path, monkeypatch, phase, damage):
    """Reading twice, each point's bin key is cached in pass one and read back in the cutoffs and pass two:
    the cache changed at any phase is exit 11, one line naming the folder, nothing left, no output."""
    from prism_stream.engines import reads

    temp = tmp_path / "tmp"
    temp.mkdir()
    if phase == "pass one":
        real, calls = reads.KeyCache.append, [0]

        def append(self, values):
            calls[0] += 1
            if calls[0] == 3:
                CACHE_DAMAGES[damage](_work(temp))
            return real(self, values)
        monkeypatch.setattr(reads.KeyCache, "append", append)
    else:
        _hook(monkeypatch, phase, CACHE_DAMAGES[damage], temp)
    out = tmp_path / "out.parquet"
    with pytest.raises(TempDataChanged) as caught:
        prism_stream.sample(str(cloud), str(out), ratio=0.05, chunk_size=20_000, temp_dir=str(temp), reads="two")
    message = str(caught.value)
    assert caught.value.exit_code == 11 and message.startswith(f"{temp}: temporary data was changed"), message
    assert "\n" not in message
    assert not out.exists() and os.listdir(temp) == [] and os.listdir(tmp_path) == ["tmp"]


def test_a_write_after_a_truncation_and_an_interrupt_are_told_apart(tmp_path):
    """Zeros written into a truncated key cache (a refile's overwrite) would hide the cut from the next mark:
    the write refuses first. An interrupt between a write and its mark is the interrupt, not a change."""
    from prism_stream.errors import Interrupted
    from prism_stream.run.staging import ArrayFile

    with staging.work_dir(str(tmp_path)) as work:
        f = ArrayFile(work, "keys.u32")
        f.append(np.arange(1000, dtype=np.uint32))
        os.truncate(f.path, 400)
        with pytest.raises(TempDataChanged, match="keys.u32 was truncated"):
            f.overwrite_zero(10, 5)
        f.close()
    with pytest.raises(Interrupted):
        with staging.work_dir(str(tmp_path)) as work:
            f = ArrayFile(work, "keys.u32")
            f.append(np.arange(10, dtype=np.uint32))
            with open(f.path, "ab") as other:  # as if our own write had landed and its mark had not
                other.write(b"\0" * 8)
            raise Interrupted("interrupted")
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("damage", ["truncated", "garbage"])
def test_heaps_set_aside_and_changed_during_a_compaction_are_one_line(cloud, tmp_path, monkeypatch, damage):
    """A compaction sets the filter's heaps aside in the spill's folder (heaps.aside) while it runs; changed
    there by another process, they are never read back as heaps: one line, exit 11, nothing left."""
    from prism_stream.core.candidates import CandidateFilter

    temp = tmp_path / "tmp"
    temp.mkdir()
    monkeypatch.setattr(spill_mod.Spill, "_due", lambda self, more: True)
    real = CandidateFilter.standing_rules

    def damaged(self, *a, **kw):
        assert self.pool is None and self.below is None  # set aside while the compaction runs
        path = os.path.join(_work(temp), "heaps.aside")
        size = os.path.getsize(path)
        if damage == "truncated":
            with open(path, "r+b") as f:
                f.truncate(size // 2)
        else:
            os.unlink(path)
            with open(path, "wb") as f:
                f.write(np.random.default_rng(2).bytes(size))
        return real(self, *a, **kw)

    monkeypatch.setattr(CandidateFilter, "standing_rules", damaged)
    out = tmp_path / "out.parquet"
    with pytest.raises(TempDataChanged) as caught:
        prism_stream.sample(str(cloud), str(out), ratio=0.05, chunk_size=20_000, temp_dir=str(temp))
    assert caught.value.exit_code == 11 and "heaps.aside" in str(caught.value) and "\n" not in str(caught.value)
    assert not out.exists() and os.listdir(temp) == []


# what a read-only folder does at each phase: the files a run has open stay writable, and the one file a phase
# makes (a compaction's heaps.aside, its survivors written in place) is one it does without when refused (the
# heaps stay in memory), so no phase meets it
READ_ONLY = ["pass one", "compaction", "between", "pass two"]


@pytest.mark.parametrize("phase", READ_ONLY)
def test_a_temporary_folder_made_read_only_is_harmless_and_leaves_nothing(cloud, tmp_path, phase):
    """The run's work folder and its files made read-only by another hand, at each phase: the run writes only
    to files it has open (or does without the one it makes), so it ends as an undisturbed run does, with the
    same output, and nothing is left in the temporary folder (the run makes its own folder writable again to
    remove it). Before the compaction wrote in place it made new files, and ended with exit 8 here."""
    import subprocess
    import sys

    import pyarrow.parquet as pq

    from conftest import user_env
    from test_hostile import _obey_permissions

    temp = tmp_path / "tmp"
    temp.mkdir()
    ref = tmp_path / "ref.parquet"
    prism_stream.sample(str(cloud), str(ref), ratio=0.05, chunk_size=20_000, temp_dir=str(temp))
    out = tmp_path / "out.parquet"
    args = [str(cloud), str(out), "--ratio", "0.05", "--chunk-size", "20000", "--temp-dir", str(temp), "--quiet",
            "--reads", "one"]
    done = subprocess.run([sys.executable, os.path.join(os.path.dirname(__file__), "faultrun.py"), phase,
                           "read-only", str(temp), "--", *args], capture_output=True, text=True, timeout=120,
                          env=user_env(PRISM_STREAM_MEMORY_POINTS="0"), preexec_fn=_obey_permissions)
    assert done.returncode == 0, done.stderr
    assert done.stderr == "" and pq.read_table(out).equals(pq.read_table(ref))
    assert os.listdir(temp) == [], "the run left its read-only folder behind"


def test_temporary_files_out_of_room_are_exit_8_naming_the_folder(cloud, tmp_path, monkeypatch, capsys):
    """A temporary file the run cannot do without that meets a full disk (here `rank`'s rank files): exit 8,
    one line naming the temporary folder, no output, nothing left in it."""
    import errno

    from conftest import cli

    real = staging.ArrayFile.append

    def append(self, values):
        if os.path.basename(self.path).startswith("rank."):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), self.path)
        return real(self, values)

    monkeypatch.setattr(staging.ArrayFile, "append", append)
    temp = tmp_path / "tmp"
    temp.mkdir()
    out = tmp_path / "out.parquet"
    code, _, err = cli(capsys, "rank", cloud, out, "--max-ratio", "0.05", "--temp-dir", temp, "--quiet")
    assert code == 8, err
    assert err.count("\n") == 1 and f"{temp}" in err and "cannot write the temporary files" in err, err
    assert not out.exists() and os.listdir(temp) == []


# -- a Dask run's staging folder: the units' spills, read back by other tasks -------------------------------

def _unit_spills(root) -> list[str]:
    """The units' spill folders under ``root`` (in the output's staging folder), finished ones first."""
    found = [os.path.join(d, n) for d, _, files in os.walk(root) if os.path.basename(d) == ".spill"
             for n in sorted(os.listdir(d))]
    return sorted(found, key=lambda f: not os.path.exists(os.path.join(f, "spill.meta")))


def _damage_unit(damage: str, root) -> None:
    folder = _unit_spills(root)[0]
    if damage == "removed":
        shutil.rmtree(folder)
        return
    {"truncated": truncate, "emptied": empty, "garbage": garbage}[damage](folder)


@pytest.mark.parametrize("damage", ["truncated", "emptied", "garbage", "removed"])
@pytest.mark.parametrize("phase", ["pass one", "cutoffs", "pass two"])
def test_a_changed_unit_spill_on_dask_is_one_line_and_leaves_nothing(cloud, tmp_path, monkeypatch, phase, damage):
    """A Dask run reading once: a finished unit's spill in the staging folder truncated, emptied, replaced
    with garbage of the same size, or removed, while other units still scan (pass one), before the cutoffs
    read the spills, or before pass two: exit 11, one line naming the staging folder, no output, nothing
    left beside it."""
    distributed = pytest.importorskip("distributed")
    from prism_stream.engines import dask as dask_engine
    from prism_stream.engines.dask import driver

    out = tmp_path / "out"
    if phase == "pass one":
        real, calls = driver.OnCluster._unit_done, [0]

        def done(self, *a, **kw):
            got = real(self, *a, **kw)
            calls[0] += 1
            if calls[0] == 2:
                _damage_unit(damage, tmp_path)
            return got
        monkeypatch.setattr(driver.OnCluster, "_unit_done", done)
    else:
        name = "select" if phase == "cutoffs" else "write"
        real_step = getattr(driver.OnCluster, name)

        def step(self, *a, **kw):
            _damage_unit(damage, tmp_path)
            return real_step(self, *a, **kw)
        monkeypatch.setattr(driver.OnCluster, name, step)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as c:
        with pytest.raises(TempDataChanged) as caught:
            dask_engine.sample(c, [str(cloud)], str(out), ratio=0.05, unit_size=40_000, reads="one")
    message = str(caught.value)
    assert caught.value.exit_code == 11 and "temporary data was changed" in message, message
    assert ".spill" in message and "\n" not in message
    assert os.listdir(tmp_path) == [], os.listdir(tmp_path)


@pytest.mark.parametrize("phase", ["dask pass one", "dask cutoffs", "dask pass two"])
def test_a_staging_folder_made_read_only_on_dask_is_exit_8_and_leaves_nothing(cloud, tmp_path, phase):
    """A Dask run's staging folder (the units' spills, and the parts pass two writes) made read-only by another
    hand: in pass one the units still to start cannot make their spill folders, in the cutoffs and pass two
    the parts cannot be written: exit 8, one line naming the folder, nothing left beside the output."""
    import subprocess
    import sys

    pytest.importorskip("distributed")
    from conftest import user_env
    from test_hostile import _obey_permissions

    outs = tmp_path / "outs"
    outs.mkdir()
    args = [str(cloud), str(outs / "out"), "--ratio", "0.05", "--dask", "local:1", "--reads", "one", "--quiet"]
    script = os.path.join(os.path.dirname(__file__), "faultrun.py")
    done = subprocess.run([sys.executable, script, phase, "read-only", str(outs), "--", *args], capture_output=True,
                          text=True, timeout=180, env=user_env(FAULTRUN_DASK_UNIT="40000"),
                          preexec_fn=_obey_permissions)
    assert done.returncode == 8, done.stderr
    assert done.stderr.count("\n") == 1 and f"{outs}{os.sep}.out." in done.stderr, done.stderr
    assert os.listdir(outs) == [], os.listdir(outs)
