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

import atexit
import contextlib
import os
import posixpath
import re
import sys
import tempfile
import threading
import time
import warnings

from ..errors import (InputNotFound, Interrupted, OutputError, OutputExists, PrismError, PrismWarning, StorageError,
                      UsageError)
from . import staging
from .staging import gib

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
        raise UsageError(f"reading or writing {name}:// needs fsspec: pip install '.[{extra}]' in the clone",
                         url) from None
    options = bounded(name, dict(storage_options(url) if options is None else options))
    key = (name, repr(sorted(options.items())))
    try:
        cls = fsspec.get_filesystem_class(name)
    except (ImportError, ValueError) as exc:
        package, extra = _BACKENDS.get(name, (None, None))
        if package is None:
            raise UsageError(f"no filesystem for {name}:// ({exc})", url) from None
        raise UsageError(f"{name}:// needs {package}: pip install '.[{extra}]' in the clone", url) from None
    fs = _FILESYSTEMS.get(key)
    if fs is None:
        with failures(url):
            fs = _FILESYSTEMS[key] = cls(**options)
        if name in ("s3", "s3a"):
            fs.retries = 1  # s3fs's own retry loop, on top of botocore's attempts: one try, the SDK retries
    return fs, cls._strip_protocol(url)


TIMEOUT_VAR = "PRISM_STREAM_STORE_TIMEOUT"
STORE_TIMEOUT = 8.0  # seconds a store may take to connect, or stay silent while it answers, before a retry
STORE_ATTEMPTS = 3  # tries of a request in all (botocore's standard retry mode), unless AWS_MAX_ATTEMPTS says


def store_timeout() -> float:
    """Seconds of silence (connecting, or between bytes of an answer) before a store request is retried:
    ``PRISM_STREAM_STORE_TIMEOUT``, else 8. A store that stops answering fails the run within about
    attempts x timeout (24 s, and the backoff between tries) instead of hanging on the SDKs' defaults
    (60 s a try, five tries)."""
    raw = os.environ.get(TIMEOUT_VAR)
    try:
        value = float(raw) if raw else STORE_TIMEOUT
    except ValueError:
        raise UsageError(f"{TIMEOUT_VAR}={raw!r} is not a number of seconds") from None
    if not 0 < value < 86400:
        raise UsageError(f"{TIMEOUT_VAR}={raw!r} must be a number of seconds above 0")
    return value


def bounded(name: str, options: dict) -> dict:
    """``options`` with the store client's waits bounded (:func:`store_timeout`), unless given already."""
    timeout = store_timeout()
    if name in ("s3", "s3a"):
        config = dict(options.get("config_kwargs") or {})
        config.setdefault("connect_timeout", timeout)
        config.setdefault("read_timeout", timeout)
        attempts = os.environ.get("AWS_MAX_ATTEMPTS")  # the AWS SDKs' meaning: tries in all
        config.setdefault("retries", {"total_max_attempts": int(attempts) if attempts and attempts.isdigit()
                                      else STORE_ATTEMPTS,
                                      "mode": os.environ.get("AWS_RETRY_MODE") or "standard"})
        options["config_kwargs"] = config
    elif name in ("http", "https") and "client_kwargs" not in options:
        try:
            import aiohttp
        except ImportError:  # fsspec's own lookup says what to install
            return options
        options["client_kwargs"] = {"timeout": aiohttp.ClientTimeout(total=None, sock_connect=timeout,
                                                                     sock_read=timeout)}
        options["get_client"] = _retrying_client
    return options


HTTP_BACKOFF = 0.5  # seconds before an HTTP request's second try, doubled before each one after


def _transient(exc: BaseException | None = None, status: int | None = None) -> bool:
    """Whether an HTTP failure may pass if tried again: a refused or reset connection, a timeout, a body cut
    short, an error status of the server's (5xx) or 429; by type and status, as :func:`failure` decides."""
    if status is not None:
        return status >= 500 or status == 429
    return any(_connection_failure(e) or _timed_out(e) for e in _causes(exc)) or _body_cut(exc)


def _body_cut(exc: BaseException) -> bool:
    """Whether an HTTP answer's body ended before its announced length, by type."""
    aiohttp = sys.modules.get("aiohttp")
    return aiohttp is not None and any(isinstance(e, aiohttp.ClientPayloadError) for e in _causes(exc))


def _silence(name: str) -> str:
    """What a request the store never answered says (fsspec's FSTimeoutError says nothing but its name)."""
    return f"no answer within {store_timeout():g} s a try, {TIMEOUT_VAR}; {name}"


async def _retry_middleware(request, handler):
    """aiohttp's client middleware: an HTTP request tried up to STORE_ATTEMPTS times in all, as S3's are,
    on a transient failure; a range read's body is read here (its size is bounded by the read block), so a
    body cut short is tried again too."""
    import asyncio

    for attempt in range(STORE_ATTEMPTS):
        last = attempt + 1 == STORE_ATTEMPTS
        try:
            response = await handler(request)
            if not last and _transient(status=response.status):
                response.release()
            else:
                if request.headers.get("Range") and response.status < 300:
                    await response.read()  # fsspec reads it whole anyway; a cut is raised here, inside the loop
                return response
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # noqa: BLE001 - sorted by _transient
            if last or not _transient(exc):
                raise
        await asyncio.sleep(HTTP_BACKOFF * 2 ** attempt)
    raise AssertionError("unreachable")


async def _retrying_client(**kwargs):
    """fsspec's HTTP client session, with :func:`_retry_middleware`."""
    import aiohttp

    return aiohttp.ClientSession(middlewares=(_retry_middleware,), **kwargs)


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


def _status(exc: BaseException) -> int | None:
    """The HTTP status a store answered with, from the exception or one it was raised from (aiohttp's
    ClientResponseError.status, botocore's ResponseMetadata), or None when no answer came."""
    for e in _causes(exc):
        status = getattr(e, "status", None)
        if isinstance(status, int) and 100 <= status < 600:
            return status
        response = getattr(e, "response", None)
        code = response.get("ResponseMetadata", {}).get("HTTPStatusCode") if isinstance(response, dict) else None
        if isinstance(code, int):
            return code
    return None


def _not_reached(exc: BaseException) -> bool:
    """Whether a "not found" hides a store that never answered: fsspec's HTTP filesystem raises
    FileNotFoundError for whatever made its HEAD and GET fail (a refused connection, an unknown host, a
    timeout, a 500). Only a 404 or 410 means the object is missing; any other status, or none, is the store's
    failure (exit 10), decided by the exception types and the status code, never by words."""
    status = _status(exc)
    if status is not None:
        return status not in (404, 410)
    return any(_connection_failure(e) for e in list(_causes(exc))[1:])


def _connection_failure(exc: BaseException) -> bool:
    """A refused or reset connection, an unknown host or a timeout, by type (the SDKs' own or the OS's)."""
    asyncio = sys.modules.get("asyncio")  # loaded by every store that could raise its timeout; not by a local run
    if isinstance(exc, (ConnectionError, TimeoutError)) or (asyncio is not None
                                                             and isinstance(exc, asyncio.TimeoutError)):
        return True
    aiohttp = sys.modules.get("aiohttp")
    if aiohttp is not None and isinstance(exc, (aiohttp.ClientConnectionError, aiohttp.ServerTimeoutError)):
        return True  # a reset, an SSL failure, an unknown host, a server that hung up
    name = type(exc).__name__.lower()
    return type(exc).__module__.split(".")[0] in ("aiohttp", "botocore", "aiobotocore", "urllib3") and (
        "connect" in name or "timeout" in name or "endpoint" in name)


def _timed_out(exc: BaseException) -> bool:
    """Whether the store stopped answering (a timeout of ours or the SDK's), by type."""
    asyncio = sys.modules.get("asyncio")
    return any(isinstance(e, TimeoutError) or (asyncio is not None and isinstance(e, asyncio.TimeoutError))
               or "timeout" in type(e).__name__.lower() for e in _causes(exc))


def _no_credentials(exc: BaseException) -> bool:
    """Whether the store failed for want of credentials, by the SDK's exception types (botocore's
    NoCredentialsError, PartialCredentialsError, CredentialRetrievalError...), not by the message."""
    return any("credential" in type(e).__name__.lower() for e in _causes(exc))


def failure(exc: BaseException, path: str, writing: bool | str = False) -> PrismError | None:
    """The one-line error of a store's failure on ``path`` (None: not the store's, e.g. a corrupt file).
    ``writing``: ``path`` is the output (its errors are exit 8, the output's); a string says what was being
    done to it (default: uploading it)."""
    if isinstance(exc, PrismError):
        return exc
    text = _first_line(exc)
    if isinstance(exc, FileNotFoundError) and _not_reached(exc):
        cause = list(_causes(exc))[-1]
        status = _status(exc)
        said = f"HTTP {status}" if status else f"{type(cause).__name__}: {_first_line(cause)}"
        if not status and _timed_out(exc):
            said = _silence(type(cause).__name__)
        if status in (401, 403):
            return (OutputError if writing else InputNotFound)(f"access denied by the store ({said})", path)
        return (OutputError if writing else StorageError)(f"the store could not be reached or failed ({said})",
                                                          path)
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
        doing = writing if isinstance(writing, str) else "cannot upload the output" if writing else "the store failed"
        if _timed_out(exc):
            return error(f"{doing}: {_silence(name)}", path)
        return error(f"{doing}: {name}: {text}", path)
    return None


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


@contextlib.contextmanager
def failures(path: str, writing: bool | str = False):
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


def kind(url: str, writing: bool | str = False) -> str | None:
    """``file``, ``directory`` or None (no such object; a missing bucket is an error)."""
    fs, path = filesystem(url)
    with failures(url, writing):
        try:
            info = fs.info(path)
        except FileNotFoundError as exc:
            if _missing_bucket(exc) or _not_reached(exc):
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


COPY_BLOCK = 8 << 20  # bytes a read when copying a file from a server that answers no range requests
_COPIES: dict[str, str] = {}  # URL -> its local copy (a server without range requests), removed at exit
_RANGED: dict[str, tuple[bool, int | None]] = {}  # URL -> (whether its server answers range requests, its size)
_COPYING = {"folder": None, "refuse": None}  # where copies go; why they cannot be made (a cluster run)


def copies_to(folder: str | None, refuse: str | None = None) -> None:
    """Where a file from a server without range requests is copied before it is read (None: the system's
    temporary folder); ``refuse``: the reason no copy may be made (the run then stops with it)."""
    _COPYING.update(folder=folder, refuse=refuse)


def _ranged(fs, inner: str, path: str) -> tuple[bool, int | None]:
    """(whether the HTTP server of ``path`` answers a range request, the size it gives or None), from one
    read of one byte past the start: fsspec's HTTP file refuses a whole-file answer to it with a ValueError,
    since it cannot seek."""
    if path not in _RANGED:
        with failures(path), fs.open(inner, "rb", block_size=1024) as f:
            ranged = True
            if f.size is None or f.size >= 2:
                try:  # a server that says Accept-Ranges: none, or gives no size, opens as a stream: no seek
                    f.seek(1)
                    f.read(1)
                except ValueError:
                    ranged = False
            _RANGED[path] = (ranged, f.size)
    return _RANGED[path]


def local_copy(path: str, options: dict | None = None) -> str | None:
    """A local copy of an http(s) input whose server answers no range requests (LAZ, COPC and Parquet are read
    by seeking), made once, streamed to the temporary folder; None for any other input.

    The copy's size is the server's Content-Length, checked against the folder's free space less the run's
    reserve before a byte is written; a server that gives no length, or a run that may not copy (a Dask
    cluster: each worker would copy the file), stops in one line (exit 10)."""
    if scheme(path) not in ("http", "https"):
        return None
    if path in _COPIES:
        return _COPIES[path]
    fs, inner = filesystem(path, options)
    ranged, total = _ranged(fs, inner, path)
    if ranged:
        return None
    if _COPYING["refuse"]:
        raise StorageError(f"the server answers no range requests, and {_COPYING['refuse']}", path)

    if total is None:  # a stream opened without a length: ask once more, by HEAD
        with failures(path):
            total = fs.info(inner).get("size")
    if total is None:
        raise StorageError("the server answers no range requests and gives no size, so the file can be neither "
                           "read in ranges nor copied within a known space; serve it with range requests", path)
    parent = _COPYING["folder"] or tempfile.gettempdir()
    free = staging.free_bytes(parent)
    if total > free - staging.RESERVE:
        raise StorageError(f"the server answers no range requests, and a copy ({gib(total)}) does not fit in "
                           f"{parent} ({gib(free)} free, {gib(staging.RESERVE)} kept)", path)
    warnings.warn(f"{path}: the server answers no range requests; copying the file whole ({gib(total)}) to "
                  f"{parent} before reading it", PrismWarning, stacklevel=2)
    folder = staging.make_work_folder(parent)
    local = os.path.join(folder, "copy" + os.path.splitext(inner)[1])
    try:
        for attempt in range(STORE_ATTEMPTS):  # a body cut short is copied again
            try:
                with failures(path), fs.open(inner, "rb", block_size=0) as src, open(local, "wb") as dst:
                    while True:
                        block = src.read(COPY_BLOCK)
                        if not block:
                            break
                        dst.write(block)
                break
            except StorageError as exc:  # only a cut body: the client tried each request already
                if attempt + 1 == STORE_ATTEMPTS or not _body_cut(exc.__context__ or exc):
                    raise
                time.sleep(HTTP_BACKOFF * 2 ** attempt)
        if os.path.getsize(local) != total:
            raise StorageError(f"the server sent {os.path.getsize(local)} bytes of the {total} it announced", path)
    except BaseException:
        staging.remove(folder)  # a copy cut short is nobody's
        raise
    _COPIES[path] = local
    if len(_COPIES) == 1:
        atexit.register(drop_copies)
    return local


def drop_copies() -> None:
    """Remove the local copies this process made."""

    for local in _COPIES.values():
        staging.remove(os.path.dirname(local))
    _COPIES.clear()


def open_input(path: str, options: dict | None = None, block_size: int = READ_BLOCK):
    """A binary file object for reading ``path`` (a local file, or a remote one fsspec reads in ranges)."""
    if not is_remote(path):
        return open(path, "rb")
    local = local_copy(path, options)
    if local is not None:
        return open(local, "rb")
    fs, inner = filesystem(path, options)
    with failures(path):
        return fs.open(inner, "rb", block_size=block_size, cache_type="readahead")


def arrow_input(path: str, options: dict | None = None):
    """``path`` as a pyarrow random-access file (Parquet reads its footer and row groups in ranges)."""
    import pyarrow as pa
    from pyarrow.fs import FSSpecHandler, PyFileSystem

    local = local_copy(path, options)
    if local is not None:
        return pa.OSFile(local, "rb")
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


CHECKING = "cannot check the output in the store"  # what failed when a store fails before pass one


def check_output(url: str, overwrite: bool) -> None:
    """Refuse a remote output that is a folder, or one that exists without ``overwrite``."""
    if scheme(url) in ("http", "https"):
        raise UsageError(f"{scheme(url)}:// is read-only here; write to a store (s3://, gs://, az://) or a "
                         "local file", url)
    found = kind(url, writing=CHECKING)
    if found == "directory":
        raise UsageError("is a folder in the store; give an output file name", url)
    if found == "file" and not overwrite:
        raise OutputExists.at_start(url)


UPLOAD_BLOCK = 8 << 20  # bytes a part: an output up to this size is one PUT, a larger one a multipart upload
ABORT_SECONDS = 15  # how long a failed upload waits for the store to drop what it uploaded
INTERRUPT_SECONDS = 3  # ... and an interrupted one


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
        raise OutputExists.meanwhile(url)
    target = None
    left: list[str] = []  # what the store kept of a failed upload
    try:
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
                _close(done, left)
            except BaseException as exc:
                if target is not None:
                    _discard(target, exc, left)
                raise
    except PrismError as error:
        if left:
            error.message += f"; {left[0]}"
        raise


def remove(urls, seconds: float = ABORT_SECONDS) -> list[str]:
    """Delete objects this run uploaded (undoing a folder's publication), waiting at most ``seconds`` in all
    (a store that is down would hold the run in retries); returns the ones not confirmed deleted."""
    urls = [urls] if isinstance(urls, str) else list(urls)
    if not urls:
        return []
    gone: list[str] = []

    def delete():
        for url in urls:
            with contextlib.suppress(BaseException):
                fs, inner = filesystem(url)
                fs.rm_file(inner)
                gone.append(url)

    _within(seconds, delete)
    return [u for u in urls if u not in gone]


def _within(seconds: float, work) -> bool:
    """Run ``work()`` (a store's cleanup) in a daemon thread and wait for it at most ``seconds``: a store that
    is down would otherwise hold the run in its retries, past every signal. Returns whether it ended without
    an error within the time; the error itself is not reported."""
    done = []

    def run():
        with contextlib.suppress(BaseException):
            work()
            done.append(True)

    worker = threading.Thread(target=run, name="prism-stream-store-cleanup", daemon=True)
    worker.start()
    worker.join(seconds)
    return bool(done)


def _close(target, left: list | None = None) -> None:
    """Finish the upload (what makes the object visible); a failure inside still discards it."""
    try:
        target.close()
    except BaseException as exc:
        _discard(target, exc, left)
        raise


def _discard(target, cause: BaseException | None = None, left: list | None = None) -> None:
    """Abort the upload (S3: abort the multipart upload), waiting at most ABORT_SECONDS (after Ctrl-C or
    SIGTERM, INTERRUPT_SECONDS: the user asked to stop): a store that is down would otherwise hold the run in
    retries, past every signal. Whatever the outcome, the file object is marked closed, so that nothing
    retries the upload when it is collected. A multipart upload the store did not confirm aborted is said in
    ``left`` (its parts are kept, and billed, until it is aborted or a lifecycle rule expires it)."""
    interrupted = isinstance(cause, (KeyboardInterrupt, Interrupted))
    try:
        aborted = _within(INTERRUPT_SECONDS if interrupted else ABORT_SECONDS, target.discard)
        upload = (getattr(target, "mpu", None) or {}).get("UploadId") if not aborted else None
        if upload and left is not None:
            left.append(f"its multipart upload {upload} could not be aborted: the store keeps its parts until "
                        "it is aborted (aws s3api abort-multipart-upload) or a lifecycle rule expires it")
    finally:
        with contextlib.suppress(Exception):
            target.closed = True  # fsspec's buffered files close (and upload) what is left when collected
