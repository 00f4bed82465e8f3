"""Where the outputs go.

Two layouts: one output file for all inputs (the inputs are one cloud), or
directory mode, where the output is a folder and each input file gets its
own output at the same relative path. Directory mode stages every output in
a hidden folder inside the destination and moves them into place only when
all are written, so a failed or interrupted run leaves nothing behind.

A remote output (``s3://bucket/out.parquet``, or a folder ``s3://bucket/out/``)
is staged in the local temporary folder and uploaded when complete
(:func:`.remote.upload`): each object appears whole or not at all, and a
folder's objects are uploaded only when all are written (if one upload
fails, the ones already up are deleted).
"""

from __future__ import annotations

import contextlib
import os
import tempfile

from ..errors import Interrupted, OutputError, OutputExists, PrismError, UnsupportedFormat, UsageError
from ..formats import WRITERS, extension
from . import remote, staging
from .inputs import expand


def check_output_file(output: str, files, overwrite: bool) -> None:
    """Refuse an output file we cannot write, one that would replace an input, a folder, or one that exists."""
    if extension(output) not in WRITERS:
        known = ", ".join(sorted(WRITERS))
        folder = "" if extension(output) else "; a folder for one output per input ends with /"
        raise UnsupportedFormat(f"unknown output extension {extension(output) or '(none)'!r} (writes {known}{folder})",
                                output)
    if any(remote.real(f) == remote.real(output) for f in files):
        raise UsageError("the output would overwrite an input", output)
    if remote.is_remote(output):
        remote.check_output(output, overwrite)
        return
    if os.path.isdir(output):
        raise UsageError("is a directory; give an output file name", output)
    refuse_one_more_tile(output, files)  # first: "use --overwrite" is the wrong advice for a tile (a glob, no output)
    if os.path.exists(output) and not overwrite:
        raise OutputExists.at_start(output)


_FAMILY = {".laz": ".las", ".copc.laz": ".las", ".pq": ".parquet"}  # what one shell glob (*.laz) may match alike


def refuse_one_more_tile(output: str, files) -> None:
    """Refuse to replace (with ``--overwrite`` or without: then before the advice to give it) an existing file that
    looks like one of the tiles the inputs are: local, in the folder of an input of its format family (LAS, LAZ and COPC are one, as ``*.laz`` matches
    COPC tiles too), and neither this command's own earlier output (prism-stream's provenance in it, from inputs
    of the same names) nor a sample prism-stream wrote there from other files. Caught: ``prism-stream
    tiles/*.laz --ratio 0.01 --overwrite``, where the shell makes the last tile the output."""
    if remote.is_remote(output) or not os.path.isfile(output):
        return
    family, folder = _family(output), _folder_of(output)
    if not any(not remote.is_remote(f) and _family(f) == family and _folder_of(f) == folder for f in files):
        return
    made_from = _made_from(output)
    if made_from is not None and (made_from == _names(files) or os.path.basename(output) not in made_from):
        # this command's earlier output, or a sample written there from other files: --overwrite replaces it;
        # not a per-file output (directory mode, --per-file, batch), named after its input: that is a tile
        return
    raise UsageError("exists beside the inputs, in their format, and is not a sample prism-stream wrote: is it "
                     "one more tile (a glob given without an output)? Name the output, or delete this file first "
                     "to replace it", output)


def _family(path) -> str:
    return _FAMILY.get(extension(path), extension(path))


def _folder_of(path) -> str:
    """The folder a path's name sits in, its own links resolved but not the name's: a link among the tiles is
    where the glob found it, and it is what a run's publish replaces."""
    return os.path.realpath(os.path.dirname(os.path.abspath(os.fspath(path))))


def _made_from(path: str) -> list[str] | None:
    """The names of the inputs prism-stream wrote ``path`` from (its provenance), or None if it did not."""
    from .info import provenance

    earlier = provenance(path, extension(path))
    return None if earlier is None else _names(earlier.get("inputs") or [])


def _names(files) -> list[str]:
    return sorted(os.path.basename(str(f)) for f in files)


def output_pattern(output: str, output_format: str | None) -> tuple[str, str | None]:
    """(output, format): ``FOLDER/*.EXT`` (the Dask engine's per-tile form) is directory mode into FOLDER,
    each input's output in format EXT; any other ``*`` in an output is refused, never written as a file
    named ``*.las``. Other outputs are returned as they are."""
    if "*" not in output:
        return output, output_format
    sep = "/" if remote.is_remote(output) else os.sep
    folder, base = output.rsplit(sep, 1) if sep in output else ("", output)
    ext = extension(base)
    if "*" in folder or base != "*" + ext or ext not in WRITERS:
        known = ", ".join("*" + e for e in sorted(WRITERS))
        raise UsageError(f"an output pattern is FOLDER/*.EXT: one output per input, in format EXT ({known})",
                         output)
    fmt = ext.lstrip(".")
    if output_format is not None and output_format.lower().lstrip(".") != fmt:
        raise UsageError(f"--format {output_format} and the output pattern's *{ext} disagree", output)
    return (folder or ".") + sep, fmt


def output_stem(name: str) -> str:
    """A file name without its extension (``.copc.laz`` counts as one)."""
    if name.lower().endswith(".copc.laz"):
        return name[: -len(".copc.laz")]
    return os.path.splitext(name)[0]


def is_directory_target(output: str | None) -> bool:
    if output is not None and remote.is_remote(output):
        return output.endswith("/") or (remote.scheme(output) not in ("http", "https")
                                        and remote.kind(output, writing=remote.CHECKING) == "directory")
    return output is not None and (os.path.isdir(output) or output.endswith(("/", os.sep)))


class Commit:
    """The one commit of a run's outputs, whatever the engine: :meth:`transaction` publishes what its block
    staged when the block ends (unless the block published it already), or discards it if the block
    fails; an interrupt becomes :class:`Interrupted`, naming :attr:`named`. Subclasses stage, and
    implement :meth:`publish` and :meth:`discard`."""

    @property
    def named(self):
        """The output as the user named it."""
        return self.output

    def publish(self) -> None:
        raise NotImplementedError

    def discard(self) -> None:
        raise NotImplementedError

    def complete(self) -> bool:
        """Whether every output is in place, whole (then an interrupt leaves them, and says so)."""
        return False

    def tidy(self) -> None:
        """What a complete publish has not yet removed of its staging (an interrupt came in between)."""

    @contextlib.contextmanager
    def transaction(self):
        try:
            yield self
            self.publish()
        except KeyboardInterrupt:
            if self.complete():  # the outputs were in place when the signal came: they stay, and the line says so
                self.tidy()
                if self.named not in staging.published():
                    staging.note_published(self.named)
                raise Interrupted(INTERRUPTED_AFTER, self.named) from None
            self.discard()
            raise Interrupted("interrupted; no output was written", self.named) from None
        except BaseException:
            self.discard()
            raise


INTERRUPTED_AFTER = "interrupted after the output was written (it is complete)"


class Layout(Commit):
    """The input files, and for each output the sources written to it."""

    def __init__(self, files, rels, output, directory, output_format, overwrite):
        self.files = files
        self.rels = rels
        self.output = output
        self.directory = directory
        self.output_format = None if output_format is None else output_format.lower()  # as names are matched
        self.overwrite = overwrite
        self.staging = None
        self.created_output_dir: list[str] = []  # folders this run made for a directory-mode output
        self.published: list[str] = []
        self._pending: list[tuple[str, str]] = []

    @staticmethod
    def of(inputs, output, output_format=None, overwrite=False) -> "Layout":
        output = None if output is None else os.fspath(output)
        if output is not None:
            output, output_format = output_pattern(output, output_format)
        pairs = expand(inputs)
        files = [f for f, _ in pairs]
        rels = [r for _, r in pairs]
        directory = is_directory_target(output)
        layout = Layout(files, rels, output, directory, output_format, overwrite)
        if output_format is not None and not directory:
            raise UsageError("--format applies to directory mode; the output file's extension says the format")
        if output is not None:
            layout._check()
        return layout

    @staticmethod
    def single(output: str | None, overwrite: bool = False) -> "Layout":
        """One output file written from no input files (a query's result), or none (a plan)."""
        layout = Layout([], [], None if output is None else os.fspath(output), False, None, overwrite)
        if output is not None:
            layout._check()
        return layout

    def outputs(self) -> list[str]:
        """Every output path: the output file, or in directory mode each input's."""
        if self.output is None:
            return []
        if not self.directory:
            return [self.output]
        return [self.final_path(i) for i in range(len(self.files))]

    def final_path(self, i: int) -> str:
        """Directory mode: where input i's output lands."""
        rel = self.rels[i]
        ext = extension(rel)
        stem = output_stem(rel)
        fmt = self.output_format
        if fmt is None:
            fmt = ext.lstrip(".") if ext in WRITERS else "parquet"
        if remote.is_remote(self.output):
            return self.output.rstrip("/") + "/" + stem.replace(os.sep, "/") + "." + fmt.lstrip(".")
        return os.path.join(self.output, stem + "." + fmt.lstrip("."))

    def _check(self) -> None:
        if not self.directory:
            check_output_file(self.output, self.files, self.overwrite)
            return
        real_inputs = {remote.real(f) for f in self.files}
        if self.output_format is not None and "." + self.output_format.lstrip(".") not in WRITERS:
            known = ", ".join(sorted(w.lstrip(".") for w in WRITERS))
            raise UsageError(f"--format {self.output_format!r} is not one we write ({known})")
        finals = [self.final_path(i) for i in range(len(self.files))]
        if len(set(finals)) != len(finals):
            raise UsageError("two inputs would write the same output (same relative path)", self.output)
        every = _names(self.files)  # once, not for each output (thousands of tiles)
        for f, source in zip(finals, self.files):
            if remote.real(f) in real_inputs:
                raise UsageError("an output would overwrite an input; choose another folder or --format", f)
            if remote.is_remote(f):
                remote.check_output(f, self.overwrite)
            elif os.path.exists(f) and not self.overwrite:
                raise OutputExists.at_start(f)
            elif os.path.isfile(f) and _made_from(f) not in (every, _names([source])):
                # its provenance names every input (one cloud), or its own (--per-file, batch)
                # `prism-stream tiles/* --overwrite`, a folder among the tiles: its originals are not outputs
                raise UsageError("exists and is not this command's earlier output; delete it first to replace it", f)

    def _begin(self) -> None:
        """Create the staging folder every output is written in before it is published (on first need)."""
        if remote.is_remote(self.output):  # staged locally, then uploaded
            name = os.path.basename(self.output.rstrip("/")) + (".prism-staging" if self.directory else "")
            folder = self.output if self.directory else self.output.rsplit("/", 1)[0]
            self.staging = staging.temp_folder(os.path.join(tempfile.gettempdir(), name), uploaded_to=folder)
            return
        if not self.directory:
            self.staging = staging.temp_folder(self.output)
            return
        if not os.path.isdir(self.output):
            made, up = [], os.path.abspath(self.output)
            while not os.path.isdir(up) and os.path.dirname(up) != up:  # the folders this run makes
                made.append(up)
                up = os.path.dirname(up)
            try:
                os.makedirs(self.output)
            except OSError as exc:
                raise OutputError(f"cannot create the output folder: {exc.strerror or exc}", self.output) from None
            self.created_output_dir = made
        staging.sweep(self.output)
        self.staging = staging.temp_folder(os.path.join(self.output, ".prism-staging"))

    def planned(self, sources):
        """(output path, sources written there) for every output, as the user named it; creates nothing."""
        if self.output is None:
            return
        if not self.directory:
            yield self.output, list(sources)
            return
        for src in sources:
            yield self.final_path(src.ordinal), [src]

    def targets(self, sources):
        """(path to write, sources written there) for every output, staged until :meth:`publish`."""
        if self.staging is None:
            self._begin()
        if not self.directory:
            target = os.path.join(self.staging, os.path.basename(self.output.rstrip("/")))
            self._pending.append((target, self.output))
            yield target, list(sources)
            return
        for src in sources:
            yield self.stage(src.ordinal), [src]

    def stage(self, i: int) -> str:
        """Directory mode: the staged path of input i's output, published with the others."""
        if self.staging is None:
            self._begin()
        final = self.final_path(i)
        rel = final[len(self.output.rstrip("/")) + 1:] if remote.is_remote(final) else os.path.relpath(final, self.output)
        stage = os.path.join(self.staging, rel)
        os.makedirs(os.path.dirname(stage), exist_ok=True)
        self._pending.append((stage, final))
        return stage

    def publish(self) -> None:
        """Move every staged output onto its destination: all of them, or (on failure) none.

        Without ``overwrite`` a destination is claimed with ``link()``, which
        fails if anything appeared there since the start (another run): that
        run keeps its output and this one fails with :class:`OutputExists`.
        """
        if self.staging is None:  # nothing staged (a plan), or published already
            return
        final = self.output
        staging.check_unchanged()  # what was read from the spill or the key cache was what the run wrote there
        try:
            for stage, final in self._pending:
                if remote.is_remote(final):
                    remote.upload(stage, final, self.overwrite)
                    self.published.append(final)
                    continue
                os.makedirs(os.path.dirname(os.path.abspath(final)), exist_ok=True)
                if self.overwrite:
                    os.replace(stage, final)
                else:
                    os.chmod(stage, staging.public_mode(0o666))
                    staging.publish_new(stage, final)
                self.published.append(os.path.abspath(final))
        except PrismError as error:  # an upload failed: the objects uploaded before it are removed, or said
            left = self._unpublish()
            if left:
                more = f" and {len(left) - 3} more" if len(left) > 3 else ""
                error.message += (f"; {len(left)} output(s) this run uploaded before could not be removed from the "
                                  f"store: {', '.join(left[:3])}{more}")
            raise
        except FileExistsError:
            self._unpublish()
            raise OutputExists.meanwhile(final) from None
        except OSError as exc:
            self._unpublish()
            raise OutputError(f"cannot publish the output: {exc.strerror or exc}", final) from None
        staging.note_published(self.named)
        staging.remove(self.staging)
        self.staging = None

    def complete(self) -> bool:
        return bool(self._pending) and len(self.published) == len(self._pending)

    def tidy(self) -> None:
        if self.staging:
            staging.remove(self.staging)
            self.staging = None

    def _unpublish(self) -> list[str]:
        """Undo :meth:`publish` (while the staged files still exist): remove the destinations linked to them
        (remote: the objects this run uploaded; one it replaced with ``--overwrite`` cannot come back). Returns
        the objects the store did not confirm removed."""
        left = remote.remove([final for _, final in self._pending
                              if remote.is_remote(final) and final in self.published])
        for stage, final in self._pending:
            if remote.is_remote(final):
                continue
            try:
                if os.path.exists(stage) and os.path.samefile(stage, final):
                    os.unlink(final)
            except OSError:
                pass
        self.published = []
        return left

    def discard(self) -> None:
        if self.staging:
            self._unpublish()
            staging.remove(self.staging)
            self.staging = None
        for folder in self.created_output_dir:  # the folders this run made, deepest first: no other
            try:
                os.rmdir(folder)
            except OSError:
                break
