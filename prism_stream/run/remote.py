"""Files in object storage (``s3://``, ``gs://``, ``az://``, ``https://``...): every fsspec call in one place.

A path with a scheme other than ``file://`` is remote. Inputs are listed
(globs and folders, sorted like local ones, so the source ordinals and the
point ids are the same: SPEC 3) and read through file objects fsspec opens
(LAS/LAZ through laspy, Parquet through pyarrow); an output is written to a
local temporary file and uploaded when complete (:func:`upload`), so that
the object appears whole or not at all.

Credentials and endpoints come from each store's own configuration, never
from the command line: for S3 the ``AWS_*`` variables (``AWS_ENDPOINT_URL``
for another endpoint), ``~/.aws/config`` and ``~/.aws/credentials``, or the
machine's role; for GCS and Azure their SDKs' usual variables and files.
:func:`storage_options` carries only what a Dask worker on another machine
needs to reach the same endpoint (no secret), beside the URL.

fsspec and its store backends load on first use: ``prism-stream --help``
imports none of them.
"""

from __future__ import annotations

import contextlib
import os
import posixpath
import re

from ..errors import InputNotFound, OutputError, OutputExists, PrismError, StorageError, UsageError

_SCHEME = re.compile(r"^([a-zA-Z][a-zA-Z0-9+.-]*)://")
# the package each scheme needs, and the extra that installs it
_BACKENDS = {"s3": ("s3fs", "s3"), "s3a": ("s3fs", "s3"), "gs": ("gcsfs", "gcs"), "gcs": ("gcsfs", "gcs"),
             "az": ("adlfs", "azure"), "abfs": ("adlfs", "azure"), "abfss": ("adlfs", "azure"),
             "http": ("aiohttp", "http"), "https": ("aiohttp", "http")}
# modules whose exceptions are the store's or the network's, not the file's content
_STORE_MODULES = ("botocore", "aiobotocore", "s3fs", "aiohttp", "gcsfs", "google", "adlfs", "azure", "fsspec",
                  "urllib3", "requests")
_FILESYSTEMS: dict = {}


def scheme(path) -> str | None:
    """The URL scheme of ``path`` (``s3``, ``https``...), or None for a local path."""
    m = _SCHEME.match(os.fspath(path)) if isinstance(path, (str, os.PathLike)) else None
    return m.group(1).lower() if m else None


def is_remote(path) -> bool:
    """A path fsspec reads rather than the operating system (``file://`` counts as local)."""
    return scheme(path) not in (None, "file")


def absolute(path: str) -> str:
    """What a summary and the provenance name a file by: a URL as given, a local path made absolute."""
    return path if is_remote(path) else os.path.abspath(path)


def real(path: str) -> str:
    """What two names of one file share: the URL of an object, the real path of a local file."""
    return path if is_remote(path) else os.path.realpath(path)


def storage_options(url: str) -> dict:
    """The options a process needs to reach ``url``'s store as this one does (no credentials).

    S3: the endpoint of ``AWS_ENDPOINT_URL_S3`` or ``AWS_ENDPOINT_URL``, so a Dask worker whose
    environment lacks it still reaches the same store; credentials stay with each process's own
    configuration.
    """
    if scheme(url) in ("s3", "s3a"):
        endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
        if endpoint:
            return {"endpoint_url": endpoint}
    return {}


def filesystem(url: str, options: dict | None = None):
    """(fsspec filesystem, path inside it) for ``url``; one filesystem per store and options in a process."""
    name = scheme(url)
    try:
        import fsspec
    except ImportError:
        extra = _BACKENDS.get(name, ("", "s3"))[1]
        raise UsageError(f"reading or writing {name}:// needs fsspec: pip install 'prism-stream[{extra}]' "
                         f"(in a clone: pip install '.[{extra}]')", url) from None
    options = dict(storage_options(url) if options is None else options)
    key = (name, tuple(sorted(options.items())))
    try:
        cls = fsspec.get_filesystem_class(name)
    except (ImportError, ValueError) as exc:
        package, extra = _BACKENDS.get(name, (None, None))
        if package is None:
            raise UsageError(f"no filesystem for {name}:// ({exc})", url) from None
        raise UsageError(f"{name}:// needs {package}: pip install 'prism-stream[{extra}]' "
                         f"(in a clone: pip install '.[{extra}]')", url) from None
    fs = _FILESYSTEMS.get(key)
    if fs is None:
        with failures(url):
            fs = _FILESYSTEMS[key] = cls(**options)
    return fs, cls._strip_protocol(url)


def _causes(exc: BaseException):
    """``exc`` and the exceptions it was raised from (fsspec's stores raise theirs from the SDK's)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


def _missing_bucket(exc: BaseException) -> bool:
    """Whether a store's FileNotFoundError is about the bucket, by the SDK's error code (S3's NoSuchBucket, or
    a 404 to HeadBucket), never by the words of the message (which hold the bucket's own name)."""
    for e in _causes(exc):
        response = getattr(e, "response", None)
        code = response.get("Error", {}).get("Code") if isinstance(response, dict) else None
        if code == "NoSuchBucket" or code in ("404", "NotFound") and getattr(e, "operation_name", "") == "HeadBucket":
            return True
    return False


def _no_credentials(exc: BaseException) -> bool:
    """Whether the store failed for want of credentials, by the SDK's exception types (botocore's
    NoCredentialsError, PartialCredentialsError, CredentialRetrievalError...), not by the message."""
    return any("credential" in type(e).__name__.lower() for e in _causes(exc))


def failure(exc: BaseException, path: str, writing: bool = False) -> PrismError | None:
    """The one-line error of a store's failure on ``path`` (None: not the store's, e.g. a corrupt file)."""
    if isinstance(exc, PrismError):
        return exc
    text = _first_line(exc)
    if isinstance(exc, FileNotFoundError):
        what = "no such bucket" if _missing_bucket(exc) else "no such object"
        return (OutputError if writing else InputNotFound)(f"{what} ({text})" if what not in text else text, path)
    if isinstance(exc, PermissionError):
        return (OutputError if writing else InputNotFound)(f"access denied by the store ({text}); check the "
                                                           "credentials it is given", path)
    module = type(exc).__module__.split(".")[0]
    if module in _STORE_MODULES or isinstance(exc, (ConnectionError, TimeoutError)) or (
            isinstance(exc, OSError) and not isinstance(exc, (IsADirectoryError, NotADirectoryError))):
        name = type(exc).__name__
        error = OutputError if writing else StorageError
        if _no_credentials(exc):
            return error(f"no credentials for the store ({name}: {text}); set them as its SDK expects "
                         "(for S3: AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY, AWS_PROFILE, ~/.aws)", path)
        return error(f"{'cannot upload the output: ' if writing else 'the store failed: '}{name}: {text}", path)
    return None


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


@contextlib.contextmanager
def failures(path: str, writing: bool = False):
    """Turn the store's failures (missing object, no credentials, network) into one-line errors.

    Nothing for a local path: its failures are the operating system's, reported where they happen.
    """
    if not is_remote(path):
        yield
        return
    try:
        yield
    except PrismError:
        raise
    except Exception as exc:  # noqa: BLE001 - sorted by failure()
        mapped = failure(exc, path, writing)
        if mapped is None:
            raise
        raise mapped from None


# ---------------------------------------------------------------- listing inputs


def _url(fs, path: str, like: str) -> str:
    """A path fsspec listed, as a URL in the scheme the user wrote."""
    name = scheme(like)
    return f"{name}://{path}" if name not in ("http", "https") else path


def kind(url: str, writing: bool = False) -> str | None:
    """``file``, ``directory`` or None (no such object; a missing bucket is an error)."""
    fs, path = filesystem(url)
    with failures(url, writing):
        try:
            info = fs.info(path)
        except FileNotFoundError as exc:
            if _missing_bucket(exc):
                raise
            return None
    return "directory" if info.get("type") == "directory" else "file"


def glob(pattern: str) -> list[str]:
    """The files a remote glob matches, sorted by path, as local globs are.

    As a local glob, a wildcard matches no hidden name (one that starts with a dot) unless the pattern
    spells a dot there itself.
    """
    fs, path = filesystem(pattern)
    with failures(pattern):
        found = fs.glob(path, detail=True)
    dotted = "/." in "/" + path
    return sorted(_url(fs, p, pattern) for p, info in found.items() if info.get("type") != "directory"
                  and (dotted or not any(part.startswith(".") for part in p.split("/"))))


def walk(folder: str) -> list[tuple[str, str]]:
    """(URL, path relative to ``folder``) of every file under a remote folder, sorted; hidden folders skipped."""
    fs, path = filesystem(folder)
    path = path.rstrip("/")
    with failures(folder):
        found = fs.find(path)
    out = []
    for p in found:
        rel = posixpath.relpath(p, path)
        if any(part.startswith(".") for part in rel.split("/")[:-1]):
            continue
        out.append((_url(fs, p, folder), rel))
    return sorted(out)


# ---------------------------------------------------------------- reading


READ_BLOCK = 16 << 20  # bytes a ranged read fetches ahead when streaming a remote file
PROBE_BLOCK = 64 << 10  # ... and when probing its header and VLRs


def open_input(path: str, options: dict | None = None, block_size: int = READ_BLOCK):
    """A binary file object for reading ``path`` (a local file, or a remote one fsspec reads in ranges)."""
    if not is_remote(path):
        return open(path, "rb")
    fs, inner = filesystem(path, options)
    with failures(path):
        return fs.open(inner, "rb", block_size=block_size, cache_type="readahead")


def arrow_input(path: str, options: dict | None = None):
    """``path`` as a pyarrow random-access file (Parquet reads its footer and row groups in ranges)."""
    from pyarrow.fs import FSSpecHandler, PyFileSystem

    fs, inner = filesystem(path, options)
    with failures(path):
        return PyFileSystem(FSSpecHandler(fs)).open_input_file(inner)


def size(path: str, options: dict | None = None) -> int:
    """Bytes in ``path``."""
    if not is_remote(path):
        return os.path.getsize(path)
    fs, inner = filesystem(path, options)
    with failures(path):
        return int(fs.size(inner))


# ---------------------------------------------------------------- writing


def check_output(url: str, overwrite: bool) -> None:
    """Refuse a remote output that is a folder, or one that exists without ``overwrite``."""
    if scheme(url) in ("http", "https"):
        raise UsageError(f"{scheme(url)}:// is read-only here; write to a store (s3://, gs://, az://) or a "
                         "local file", url)
    found = kind(url, writing=True)
    if found == "directory":
        raise UsageError("is a folder in the store; give an output file name", url)
    if found == "file" and not overwrite:
        raise OutputExists("already exists (use --overwrite to replace it)", url)


UPLOAD_BLOCK = 8 << 20  # bytes a part: an output up to this size is one PUT, a larger one a multipart upload


def upload(local: str, url: str, overwrite: bool) -> None:
    """Copy the finished file ``local`` to ``url``: the object appears complete or not at all.

    The store's file object uploads in parts and makes the object visible
    only when it is closed (S3: a single PUT, or a multipart upload
    completed at the end; GCS: a resumable upload finalized at the end;
    Azure: blocks committed at the end). Any failure before that, an
    interrupt included, discards the upload (S3: the multipart upload is
    aborted), so nothing is left to see or to pay for.

    Without ``overwrite`` an object that appeared since the run started is
    not replaced; the check and the upload are two requests, so two runs
    racing for one name may both write it (the last one wins whole).
    """
    fs, inner = filesystem(url)
    if not overwrite and kind(url, writing=True) is not None:
        raise OutputExists("was written by another run meanwhile (use --overwrite to replace it)", url)
    target = None
    with failures(url, writing=True):
        try:
            target = fs.open(inner, "wb", block_size=UPLOAD_BLOCK)
            with open(local, "rb") as f:
                while True:
                    block = f.read(UPLOAD_BLOCK)
                    if not block:
                        break
                    target.write(block)
            done, target = target, None
            _close(done)
        except BaseException:
            if target is not None:
                _discard(target)
            raise


def remove(url: str) -> None:
    """Delete an object this run uploaded (undoing a folder's publication); a failure is not reported."""
    fs, inner = filesystem(url)
    with contextlib.suppress(Exception):
        fs.rm_file(inner)


def _close(target) -> None:
    """Finish the upload (what makes the object visible); a failure inside still discards it."""
    try:
        target.close()
    except BaseException:
        _discard(target)
        raise


def _discard(target) -> None:
    with contextlib.suppress(Exception):
        target.discard()
