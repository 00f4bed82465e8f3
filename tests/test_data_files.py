"""The committed test data is what tests/data/README.md says it is: the same files, unmodified.

The README lists every file's origin and its SHA-256; a file added, removed
or changed without the README saying so fails here, so the record of where
each cloud comes from (and under which license) cannot drift from the data.
"""

from __future__ import annotations

import hashlib
import re

from conftest import DATA, EDGE, REAL

README = DATA / "README.md"


def data_files() -> set[str]:
    return {f"{folder.name}/{p.name}" for folder in (REAL, EDGE) for p in folder.iterdir()}


def listed_checksums() -> dict[str, str]:
    block = re.search(r"^```sha256\n(.*?)^```", README.read_text(), re.S | re.M)
    assert block, "tests/data/README.md has no ```sha256 block"
    pairs = [line.split("  ", 1) for line in block.group(1).splitlines() if line.strip()]
    return {name: digest for digest, name in pairs}


def test_every_file_has_its_checksum_and_no_other():
    assert set(listed_checksums()) == data_files()


def test_every_file_is_unmodified():
    for name, digest in sorted(listed_checksums().items()):
        assert hashlib.sha256((DATA / name).read_bytes()).hexdigest() == digest, name


def test_every_file_has_an_origin_row():
    """Each file has a table row naming its repository, path, full commit and license."""
    rows = re.findall(r"^\| `([^`]+)` \| `([\w.-]+/[\w.-]+)` \| `([^`]+)` \| `([0-9a-f]{40})` \| ([^|]+) \|",
                      README.read_text(), re.M)
    assert sorted(r[0] for r in rows) == sorted(name.split("/", 1)[1] for name in data_files())
    assert all(license.strip() for *_, license in rows)
