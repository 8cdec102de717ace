"""Where results go: output paths checked before anything runs, folders replaced atomically.

tracklab writes only where it may, and removes only what it wrote:

* a results folder (``run``, ``sweep``, ``reproduce``) goes to a path that does not exist
  yet, an empty folder, or a folder tracklab wrote before: one holding ``stats.json``,
  ``sweep.json`` or ``tune.json`` with tracklab's header and nothing but the files tracklab
  wrote there. Every results folder holds a manifest, ``.tracklab-files`` (JSON: tracklab's
  header and ``"files"``, the names written), and only the files it lists count as
  tracklab's: a file of the user's dropped in, a figure's name included, makes it a folder
  tracklab did not write. A folder an older tracklab wrote has no manifest: there the names
  tracklab writes (``RESULTS_FILES`` and the figures, ``*.png``, ``*.pdf``, ``*.svg``) count. Anything else (a folder of the
  user's, the working folder, the experiment's own folder) is refused with one line before
  anything compiles, so the replacement below never removes a file tracklab did not write;
* a tuned experiment file (``tune --out``) goes to a new path or replaces a file that
  starts with tracklab's header line;
* the path must be creatable and writable, its name short enough for the temporary name
  written beside it, which is probed before the work starts.

Temporaries: a new folder or file is written beside its destination under a temporary name,
``.NAME.tmp-PID-TOKEN``, created exclusively (``mkdir``, ``O_EXCL``), so it never is an
existing path. TOKEN is 8 random hexadecimal digits followed by 8 of a digest of the rest of
the name: tracklab's mark, which no name of the user's carries by chance. A path without a
valid mark is never removed nor moved, whatever its name (a user's ``.res.tmp-1234`` beside
``res``, or a temporary an older tracklab left).

A new folder is swapped into place in one step: ``renameat2(RENAME_EXCHANGE)`` on Linux
(``renamex_np(RENAME_SWAP)`` on macOS), so the path holds either the previous results or the
complete new ones at every instant. Where the file system cannot exchange, the old folder is
renamed aside first (``.NAME.old-PID-TOKEN``) and restored by the next run if a kill fell
between the two renames. Marked temporaries of processes that no longer exist, holding only
what tracklab writes, are removed by the next run into the same path.

Ctrl-C (``tracklab.interrupts``): every SIGINT is recorded, even one whose
``KeyboardInterrupt`` was swallowed inside a callback, and the swap checks the record first,
with SIGINT blocked across the swap itself: an interrupted command leaves the previous results
or the complete new ones, and exits 130.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import hashlib
import json
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

from tracklab import __version__
from tracklab.errors import ConfigError
from tracklab.interrupts import note_written, raise_if_interrupted, sigint_blocked

RESULTS_DOCUMENTS = ("stats.json", "sweep.json", "tune.json")  # the file that marks a tracklab results folder
RESULTS_FILES = frozenset(RESULTS_DOCUMENTS + ("series.npz", "table.md", "table.csv", "tune.log"))  # and figures
FIGURE_SUFFIXES = (".png", ".pdf", ".svg")  # the figures' formats (report.figures.FORMATS)
MANIFEST = ".tracklab-files"  # in every results folder: the names of the files tracklab wrote there
HEADER_KEY = "tracklab_version"  # the first key of every document tracklab writes
TUNED_HEADER = "# written by tracklab tune"  # the first line of a tuned experiment file
TABLE_BEGIN, TABLE_END = "<!-- tracklab table: begin -->", "<!-- tracklab table: end -->"  # in a results README
_PID_WIDTH = 7  # /proc/sys/kernel/pid_max is at most 2**22: seven digits
_RANDOM_DIGITS = _CHECK_DIGITS = 8  # a temporary's TOKEN: random hexadecimal digits, then a digest's
TEMP_SUFFIX = len(".tmp-") + _PID_WIDTH + len("-") + _RANDOM_DIGITS + _CHECK_DIGITS  # after ".NAME"


# --- what a path is -------------------------------------------------------------------------


def _real(path) -> Path:
    return Path(os.path.realpath(os.path.abspath(path)))


def _name_max(folder: Path) -> int:
    try:
        return os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        return 255


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def is_results_document(path: Path) -> bool:
    """Whether ``path`` is a stats.json / sweep.json tracklab wrote (its header, or the keys of
    one written before the header existed)."""
    try:
        with open(path, "rb") as fh:
            doc = json.loads(fh.read())
    except (OSError, ValueError, RecursionError):
        return False
    if not isinstance(doc, dict):
        return False
    return HEADER_KEY in doc or ("experiment" in doc and ("filters" in doc or "points" in doc))


def _plain_file(path: Path) -> bool:
    return path.is_file() and not path.is_symlink()


def listed_files(folder: Path) -> frozenset[str] | None:
    """The names a results folder's manifest lists; None where it has none (an older tracklab's
    folder, or a temporary cut short) or one that is not tracklab's."""
    path = folder / MANIFEST
    if not os.path.lexists(path):
        return None
    try:
        with open(path, "rb") as fh:
            doc = json.loads(fh.read(1 << 20))
    except (OSError, ValueError, RecursionError):
        return None
    files = doc.get("files") if isinstance(doc, dict) and HEADER_KEY in doc else None
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        return None
    return frozenset(files)


def _not_written(folder: Path, entries, listed) -> list[str]:
    """The entries that are not plain files tracklab wrote into a results folder: those its
    manifest lists (``listed``), or without one the names tracklab writes there."""
    def ours(e):
        if e == MANIFEST:
            named = listed is not None
        elif listed is not None:
            named = e in listed
        else:
            named = e in RESULTS_FILES or e.endswith(FIGURE_SUFFIXES)
        return named and _plain_file(folder / e)

    return [e for e in entries if not ours(e)]


def _write_manifest(folder: Path):
    """List every file now in ``folder`` (what tracklab wrote into its temporary folder) in its manifest."""
    names = sorted(e for e in os.listdir(folder) if e != MANIFEST)
    (folder / MANIFEST).write_text(json.dumps({HEADER_KEY: __version__, "files": names}) + "\n")


def _results_document_begun(path: Path) -> bool:
    """A results document, possibly cut short while written: empty, or starting with the header."""
    with open(path, "rb") as fh:
        head = fh.read(len(HEADER_KEY) + 2)
    return not head or head == b'{"' + HEADER_KEY.encode() or is_results_document(path)


def foreign_entries(folder: Path) -> list[str]:
    """What in an existing folder tracklab did not write there (empty for a results folder)."""
    entries = sorted(os.listdir(folder))
    if not entries:
        return []
    docs = [e for e in entries if e in RESULTS_DOCUMENTS]
    if not docs or not all(is_results_document(folder / d) for d in docs):
        return entries
    return _not_written(folder, entries, listed_files(folder))


def _inside(a: Path, b: Path) -> bool:
    """Whether a is b or lies under it."""
    return a == b or b in a.parents


def _probe(folder: Path, file, field, value):
    """Create and remove a temporary folder in ``folder`` (the first existing one on the way)."""
    anc = folder
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise ConfigError(file, field, value, f"cannot be created: {anc} is not a folder")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".tracklab-probe-", dir=anc))
    except OSError as e:
        raise ConfigError(file, field, value, f"cannot be written: {e.strerror or e} in {anc}") from None


def _check_names(path: Path, file, field, value, suffix_len):
    """Every missing component within NAME_MAX, and the temporary name beside the last one."""
    anc = path
    while not anc.exists():
        anc = anc.parent
    limit = _name_max(anc if anc.is_dir() else anc.parent)
    for part in path.relative_to(anc).parts if path != anc else ():
        if len(os.fsencode(part)) > limit:
            raise ConfigError(file, field, value, f"a name in it is longer than {limit} bytes")
    need = 1 + len(os.fsencode(path.name)) + suffix_len
    if need > limit:
        raise ConfigError(file, field, value,
                          f"its name must be at most {limit - 1 - suffix_len} bytes (tracklab writes beside it "
                          f"under .NAME.tmp-PID-TOKEN first)")


def _resolve(out, file, field) -> Path:
    """The real path of ``out``; ConfigError for a path too long or through a broken or looping link."""
    value = str(out)
    try:
        limit = os.pathconf("/", "PC_PATH_MAX")
    except (OSError, ValueError, AttributeError):
        limit = 4096
    path = Path(os.path.abspath(out))
    if len(os.fsencode(str(path))) >= limit:
        raise ConfigError(file, field, value, f"the path is longer than this system's {limit - 1} bytes")
    name_max = _name_max(Path("/"))
    if any(len(os.fsencode(part)) > name_max for part in path.parts):
        raise ConfigError(file, field, value, f"a name in it is longer than {name_max} bytes")
    try:
        for p in [*reversed(path.parents), path]:
            if os.path.lexists(p) and not os.path.exists(p):
                raise ConfigError(file, field, value, f"passes through {p}, a symbolic link to nothing (or a loop)")
        return Path(os.path.realpath(path))
    except OSError as e:
        raise ConfigError(file, field, value, f"cannot be resolved: {e.strerror or e}") from None


def check_results_folder(out, file, field="--out", where=None) -> Path:
    """The real path of a results folder to be written at ``out``, or ConfigError in one line.

    ``file``: the experiment file (its folder may not be the output; None: none). A refusal
    names ``where`` (a Python function: ``tracklab.evaluate``, with ``field`` its argument
    ``out``), by default ``file`` (with ``field`` the command's option).
    """
    raise_if_interrupted()  # before anything is checked, compiled or written
    value = str(out)
    named = file if where is None else where
    real = _resolve(out, named, field)
    cwd = _real(os.getcwd())
    if _inside(cwd, real):
        raise ConfigError(named, field, value, "is the working folder or one above it: name a folder of its own")
    if file is not None and Path(file).exists() and _inside(_real(file).parent, real):
        raise ConfigError(named, field, value, "holds the experiment file: name a folder of its own")
    return _check_folder_contents(real, named, field, value)


def check_results_parent(out, experiments, field="--out") -> Path:
    """The real path of the folder ``reproduce`` writes its results folders and README.md into:
    new, empty, or one holding a README.md with tracklab's table markers (a results folder of
    tracklab's); never the working folder, one above it, or the experiments' folder."""
    raise_if_interrupted()  # before anything is checked, compiled or written
    value = str(out)
    real = _resolve(out, experiments, field)
    if _inside(_real(os.getcwd()), real):
        raise ConfigError(experiments, field, value, "is the working folder or one above it: name a folder of its own")
    if _inside(_real(experiments), real):
        raise ConfigError(experiments, field, value, "holds the experiment files: name a folder of its own")
    if real.exists():
        if not real.is_dir():
            raise ConfigError(experiments, field, value, "exists and is not a folder")
        readme = real / "README.md"
        if os.listdir(real) and not (readme.is_file() and TABLE_BEGIN in readme.read_text(errors="replace")):
            raise ConfigError(experiments, field, value,
                              f"is a folder tracklab did not write (no README.md with {TABLE_BEGIN}): "
                              f"name a new or empty folder")
    _check_names(real, experiments, field, value, 0)
    _probe(real, experiments, field, value)
    return real


def _check_folder_contents(real: Path, file, field, value) -> Path:
    if real.exists():
        if not real.is_dir():
            raise ConfigError(file, field, value, "exists and is not a folder")
        try:
            foreign = foreign_entries(real)
        except OSError as e:
            raise ConfigError(file, field, value, f"cannot be read: {e.strerror or e}") from None
        if foreign:
            shown = ", ".join(foreign[:3]) + (", …" if len(foreign) > 3 else "")
            raise ConfigError(file, field, value,
                              f"is a folder tracklab did not write (it holds {shown}): name a new or empty folder, "
                              f"or a results folder of tracklab's")
    _check_names(real, file, field, value, TEMP_SUFFIX)
    _probe(real.parent, file, field, value)
    return real


def check_tuned_file(out, file, field="--out") -> Path:
    """The real path of a tuned experiment file to be written at ``out``, or ConfigError."""
    raise_if_interrupted()  # before anything is checked, compiled or written
    value = str(out)
    real = _resolve(out, file, field)
    if real.exists():
        if real.is_dir():
            raise ConfigError(file, field, value, "is a folder: name the tuned experiment file (.toml) to write")
        try:
            with open(real, "rb") as fh:
                first = fh.read(len(TUNED_HEADER) + 1)
        except OSError as e:
            raise ConfigError(file, field, value, f"cannot be read: {e.strerror or e}") from None
        if not first.startswith(TUNED_HEADER.encode()):
            raise ConfigError(file, field, value,
                              "exists and was not written by tracklab tune: name a new file, or one tune wrote")
    _check_names(real, file, field, value, TEMP_SUFFIX)
    _probe(real.parent, file, field, value)
    return real


# --- writing -------------------------------------------------------------------------------

_TEMP_RE = re.compile(r"\.(?P<name>.+)\.(?P<what>tmp|old)-(?P<pid>[0-9]+)-(?P<random>[0-9a-f]{%d})(?P<check>[0-9a-f]{%d})"
                      % (_RANDOM_DIGITS, _CHECK_DIGITS), re.DOTALL)


def _check_digits(name: str, what: str, pid: str, random: str) -> str:
    """The second half of a temporary's TOKEN: a digest of the rest of its name."""
    text = b"\0".join([b"tracklab temporary", os.fsencode(name), what.encode(), pid.encode(), random.encode()])
    return hashlib.sha256(text).hexdigest()[:_CHECK_DIGITS]


def temporary_name(name: str, what: str = "tmp", pid: int | None = None) -> str:
    """A fresh ``.NAME.tmp-PID-TOKEN`` (``what``: tmp, or old for a folder set aside; ``pid``:
    this process's by default)."""
    pid, random = str(os.getpid() if pid is None else pid), os.urandom(_RANDOM_DIGITS // 2).hex()
    return f".{name}.{what}-{pid}-{random}{_check_digits(name, what, pid, random)}"


def temporary_of(entry: str):
    """(the output's name, tmp or old, the process id) of a name tracklab gave a temporary (its
    TOKEN checked), or None for any other name."""
    m = _TEMP_RE.fullmatch(entry)
    if m is None or m["check"] != _check_digits(m["name"], m["what"], m["pid"], m["random"]):
        return None
    return m["name"], m["what"], int(m["pid"])


def _new_temporary(out: Path, create, what="tmp") -> Path:
    """``create(path)`` at a fresh temporary name beside ``out``; ``create`` fails on an existing path."""
    for _ in range(100):
        path = out.parent / temporary_name(out.name, what)
        try:
            create(path)
            return path
        except FileExistsError:  # a name already taken: draw another
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary name", str(out.parent))


def clean_stale(out: Path):
    """Remove the temporaries beside ``out`` left by processes that no longer exist: those that
    carry tracklab's TOKEN and hold only what tracklab writes; an ``.old`` folder of a dead
    process is put back if ``out`` itself is missing."""
    parent = out.parent
    try:
        entries = os.listdir(parent)
    except OSError:
        return
    for e in entries:
        t = temporary_of(e)
        if t is None or t[0] != out.name or t[2] == os.getpid() or _pid_alive(t[2]):
            continue
        path = parent / e
        try:
            if not _written_by_tracklab(path):  # a file of the user's in it: never touched
                continue
            if t[1] == "old" and not os.path.lexists(out):
                os.rename(path, out)
                continue
            if path.is_dir():
                shutil.rmtree(path)
            else:
                os.remove(path)
        except OSError:
            continue


def _written_by_tracklab(path: Path) -> bool:
    """Whether a temporary left beside an output holds only what tracklab writes: a folder with
    nothing but the files its manifest lists, or results files (possibly cut short), or a tuned
    file or results README."""
    if path.is_symlink():
        return False
    if path.is_dir():  # possibly cut short: no document yet, or an empty one
        entries = os.listdir(path)
        return not _not_written(path, entries, listed_files(path)) and all(
            _results_document_begun(path / d) for d in entries if d in RESULTS_DOCUMENTS)
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    return not head or head.startswith(TUNED_HEADER.encode()) or TABLE_BEGIN.encode() in head


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one step; False where the system or file system cannot."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
    except OSError:
        return False
    if sys.platform.startswith("linux") and hasattr(libc, "renameat2"):
        AT_FDCWD, RENAME_EXCHANGE = -100, 2
        r = libc.renameat2(AT_FDCWD, os.fsencode(a), AT_FDCWD, os.fsencode(b), RENAME_EXCHANGE)
    elif sys.platform == "darwin" and hasattr(libc, "renamex_np"):
        RENAME_SWAP = 2
        r = libc.renamex_np(os.fsencode(a), os.fsencode(b), RENAME_SWAP)
    else:
        return False
    if r == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _rename_aside(out: Path) -> Path:
    """Rename ``out`` to a fresh ``.NAME.old-PID-TOKEN`` beside it."""
    def move(path):
        if os.path.lexists(path):
            raise FileExistsError(errno.EEXIST, "exists", str(path))
        os.rename(out, path)

    return _new_temporary(out, move, "old")


def _put_in_place(tmp: Path, out: Path):
    """Make the complete folder ``tmp`` the folder ``out``; the previous one is removed."""
    try:
        os.rename(tmp, out)  # out absent (or an empty folder)
        return
    except OSError as e:
        if e.errno not in (errno.ENOTEMPTY, errno.EEXIST):
            raise
    if _exchange(tmp, out):
        shutil.rmtree(tmp, ignore_errors=True)  # now the previous results
        return
    old = _rename_aside(out)
    os.rename(tmp, out)
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_folder(out, file=None, field="--out", where=None):
    """Yield an empty temporary folder beside ``out`` that replaces ``out`` when the block
    completes (and is removed if it does not), with its manifest listing every file written
    into it. ``out`` is checked again first (``check_results_folder``: ``file``, ``field`` and
    ``where`` as there)."""
    out = check_results_folder(out, file, field, where)
    file = file if where is None else where  # what a refusal names
    out.parent.mkdir(parents=True, exist_ok=True)
    clean_stale(out)
    tmp = _new_temporary(out, os.mkdir)
    try:
        yield tmp
        _write_manifest(tmp)
        raise_if_interrupted()
        if os.path.isdir(out) and foreign_entries(out):  # someone else's folder appeared meanwhile
            raise ConfigError(file, field, str(out), "became a folder tracklab did not write while it ran")
        with sigint_blocked():
            _put_in_place(tmp, out)
            note_written(out)
    except BaseException:
        with sigint_blocked():  # a second Ctrl-C does not cut the clean-up short
            shutil.rmtree(tmp, ignore_errors=True)
        raise


def _create_file(path: Path):
    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))


def write_text_atomically(path, text: str, verify=None):
    """Write ``path`` through a temporary file beside it, replaced in one step; ``verify(tmp)``,
    if given, may refuse the file (by raising) before it replaces anything."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_stale(path)
    tmp = _new_temporary(path, _create_file)
    try:
        tmp.write_text(text)
        if verify is not None:
            verify(tmp)
        raise_if_interrupted()
        with sigint_blocked():
            os.replace(tmp, path)
            note_written(path)
    except BaseException:
        with sigint_blocked(), contextlib.suppress(OSError):
            os.remove(tmp)
        raise
