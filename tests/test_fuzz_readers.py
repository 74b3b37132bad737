"""Fuzzing the readers: whatever a log file or a registry holds, nothing crashes and every row
read is stored or named.

* The log reader (:func:`~fleetbrake.ingest.reading.read_log`, and the per-file preparation
  the workers run) gets arbitrary bytes and structured mutations of a valid file: field counts,
  encodings, line endings, huge fields, BOMs, NUL bytes, reordered and duplicated columns,
  timestamps with offsets or without ``Z``, cut short, gzip. Allowed outcomes: a
  :class:`~fleetbrake.ingest.quarantine.Quarantine` whose reason names the file; or a parsed
  file where the data lines (counted here, independently of the reader) equal the rows stored
  plus the rows rejected, each rejected line in exactly one rejected run with its reason.
* The registry reader (:func:`~fleetbrake.fleet.registry.load_registry`) gets arbitrary text
  and bytes, generated TOML documents and mutations of a valid ``fleet.toml``. Allowed
  outcomes: a registry in which every ``[[wagon]]`` entry is loaded or named in a problem; or a
  :class:`~fleetbrake.fleet.registry.RegistryError` naming the file.

The ``@example`` cases are inputs a reader must survive that a random search seldom builds
(integers of hundreds of digits, arrays nested thousands deep, a field of a megabyte, lines
ended by a lone carriage return); the parametrized test at the end states what becomes of each
registry one.

Bounded time: the profile ``fuzz`` (the default, derandomized so that CI is reproducible)
tries :data:`FUZZ_EXAMPLES` inputs per test; ``FLEETBRAKE_FUZZ_PROFILE=fuzz-long`` selects a
random seed and ten times as many. The number of inputs each test tried is written to the
terminal after the module's tests; ``--hypothesis-show-statistics`` gives hypothesis' own
account (time per input, outcomes).
"""

from __future__ import annotations

import datetime as dt
import gzip
import math
import os
import tempfile
import tomllib
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import duckdb
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from fleetbrake.fleet import logfile as lf
from fleetbrake.fleet.registry import KEY_RANGES, RegistryError, load_registry
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.files import run_ingest
from fleetbrake.ingest.prepare import FilePartition, prepare_partition
from fleetbrake.ingest.quarantine import Quarantine
from fleetbrake.ingest.reading import read_log
from fleetbrake.ingest.scan import LogEntry
from fleetgen import T0_UTC, registry_text, simple_session, write_registry

FUZZ_EXAMPLES = 500
"""Inputs per fuzz test in the default profile (CI)."""

settings.register_profile(
    "fuzz",
    max_examples=FUZZ_EXAMPLES,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.register_profile(
    "fuzz-long",
    max_examples=10 * FUZZ_EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
FUZZ = settings.get_profile(os.environ.get("FLEETBRAKE_FUZZ_PROFILE", "fuzz"))

WAGON = "SGG-0001"
RELPATH = lf.log_relpath(WAGON, T0_UTC, gzip=False).as_posix()
CONFIG = IngestConfig()
ROWS = 12
VALID = lf.to_csv_bytes(simple_session(rows=ROWS))
QUARANTINE_CODES = {"empty", "gzip", "binary", "header", "rows"}
"""The codes the reader itself may give (the others come from the name, size or registry;
``error``, a reader failure, is never allowed)."""

TRIED: Counter[str] = Counter()
"""Inputs tried per test, written to the terminal after the module's tests."""
OUTCOMES: Counter[str] = Counter()
"""What became of the inputs: quarantined (and why), read, read with rows rejected, refused."""


@pytest.fixture(scope="module", autouse=True)
def _report_tried(request: pytest.FixtureRequest) -> Iterator[None]:
    yield
    lines = [f"fuzz: {name}: {count} inputs tried" for name, count in sorted(TRIED.items())]
    lines += [f"fuzz: {name}: {count}" for name, count in sorted(OUTCOMES.items())]
    terminal = request.config.pluginmanager.get_plugin("terminalreporter")
    capture = request.config.pluginmanager.get_plugin("capturemanager")
    if terminal is None or capture is None:
        print("\n".join(lines))
        return
    with capture.global_and_fixture_disabled():
        terminal.write_line("")
        for line in lines:
            terminal.write_line(line)


# --------------------------------------------------------------------------------------------
# The log reader


def _data_lines(data: bytes) -> int:
    """The data lines of a log file's bytes (after the header), counted without the reader:
    every newline after the first ends one, and bytes after the last newline are one more."""
    if data.startswith(b"\x1f\x8b"):
        data = gzip.decompress(data)
    body = data[data.find(b"\n") + 1 :]
    return body.count(b"\n") + int(bool(body) and not body.endswith(b"\n"))


def check_log(data: bytes, relpath: str = RELPATH) -> str:
    """Read ``data`` as the file ``relpath``; assert the invariant; return the outcome."""
    try:
        parsed = read_log(data, relpath, T0_UTC, CONFIG)
    except Quarantine as problem:
        assert problem.code in QUARANTINE_CODES, problem.code
        assert problem.reason.startswith(f"{relpath}: "), problem.reason
        OUTCOMES[f"log reader outcome: quarantined ({problem.code})"] += 1
        return f"quarantined ({problem.code})"
    repairs, frame = parsed.repairs, parsed.frame
    read = _data_lines(data)
    assert repairs.rows_in_file == read
    assert frame.height + repairs.rows_rejected == read
    named = [line for run in repairs.rejected for line in range(run.first_line, run.last_line + 1)]
    assert len(named) == len(set(named)) == repairs.rows_rejected, repairs.rejected
    assert all(2 <= line <= read + 1 for line in named)
    assert all(run.why for run in repairs.rejected)
    if repairs.rows_rejected:
        text = repairs.rejected_text()
        assert text is not None and text.startswith(f"{repairs.rows_rejected} row")
    assert frame.columns == ["time_utc", *lf.FLOAT_COLUMNS, "block_temp_raw_c", "block_temp_fault"]
    assert frame["time_utc"].null_count() == 0
    assert frame["time_utc"].is_sorted() and frame["time_utc"].n_unique() == frame.height
    outcome = "read" if not repairs.rows_rejected else "read, rows rejected"
    OUTCOMES[f"log reader outcome: {outcome}"] += 1
    return outcome


def _lines(data: bytes) -> list[bytes]:
    return data.split(b"\n")


def _on_cells(data: bytes, edit: Callable[[list[list[bytes]]], None]) -> bytes:
    """``data`` with its header and data lines split into cells, edited, joined again."""
    lines = _lines(data)
    cells = [line.split(b",") for line in lines]
    edit(cells)
    return b"\n".join(b",".join(row) for row in cells)


def _reorder(data: bytes, seed: int) -> bytes:
    """Columns in another order, the header with them (a valid file)."""
    width = len(_lines(data)[0].split(b","))
    order = sorted(range(width), key=lambda i: (i * (seed | 1) + seed) % (width + 1))

    def edit(cells: list[list[bytes]]) -> None:
        for row in cells:
            if len(row) == width:
                row[:] = [row[i] for i in order]

    return _on_cells(data, edit)


def _duplicate_column(data: bytes, column: int) -> bytes:
    def edit(cells: list[list[bytes]]) -> None:
        for row in cells:
            if row and row != [b""]:
                row.append(row[column % len(row)])

    return _on_cells(data, edit)


def _retime(data: bytes, style: str) -> bytes:
    """Every time cell respelled: an offset, no ``Z``, fractions, a space, a date only."""
    lines = _lines(data)
    for i in range(1, len(lines)):
        stamp, sep, rest = lines[i].partition(b",")
        if not stamp.endswith(b"Z"):
            continue
        base = stamp[:-1]
        lines[i] = (
            {
                "offset": base + b"+00:00",
                "offset2": base + b"+02:00",
                "noZ": base,
                "fraction": base + b".250Z",
                "space": base.replace(b"T", b" ") + b"Z",
                "date": base[:10],
                "lower": base + b"z",
            }[style]
            + sep
            + rest
        )
    return b"\n".join(lines)


def _mutate(data: bytes, kind: str, position: int, value: int) -> bytes:
    """One structured mutation of a log file's bytes at ``position`` (of the lines or bytes)."""
    lines = _lines(data)
    if len(lines) < 2:  # no data line (a file cut, or of one line): one empty line to edit
        lines.append(b"")
    line = 1 + position % (len(lines) - 1)
    if kind == "add_field":
        lines[line] += b"," + str(value).encode()
    elif kind == "drop_field":
        lines[line] = lines[line].rpartition(b",")[0]
    elif kind == "empty_line":
        lines.insert(line, b"")
    elif kind == "huge_field":
        cells = lines[line].split(b",")
        cells[value % len(cells)] = b"9" * (1 << 16 + value % 5)
        lines[line] = b",".join(cells)
    elif kind == "huge_extra_field":
        cells = lines[line].split(b",")
        cells.insert(1, b"x" * (1 << 20))
        lines[line] = b",".join(cells)
    elif kind == "crlf":
        return data.replace(b"\n", b"\r\n")
    elif kind == "cr":
        return data.replace(b"\n", b"\r")
    elif kind == "mixed_endings":
        lines[line] += b"\r"
    elif kind == "bom":
        return b"\xef\xbb\xbf" + data
    elif kind == "bom_in_line":
        lines[line] = b"\xef\xbb\xbf" + lines[line]
    elif kind == "utf16":
        return data.decode("utf-8", "replace").encode("utf-16")
    elif kind == "latin1":
        lines[line] += b",\xe9\xff"
    elif kind == "nul":
        at = position % (len(data) + 1)
        return data[:at] + b"\x00" * (1 + value % 3) + data[at:]
    elif kind == "byte":
        at = position % max(1, len(data))
        return data[:at] + bytes([value % 256]) + data[at + 1 :]
    elif kind == "cut":
        return data[: position % (len(data) + 1)]
    elif kind == "reorder":
        return _reorder(data, value)
    elif kind == "duplicate_column":
        return _duplicate_column(data, value)
    elif kind == "duplicate_line":
        lines.insert(line, lines[line])
    elif kind == "swap_lines":
        other = 1 + value % max(1, len(lines) - 1)
        lines[line], lines[other] = lines[other], lines[line]
    elif kind == "retime":
        styles = ["offset", "offset2", "noZ", "fraction", "space", "date", "lower"]
        return _retime(data, styles[value % len(styles)])
    elif kind == "quote":
        lines[line] = b'"' + lines[line].replace(b",", b'","') + b'"'
    elif kind == "nan":
        cells = lines[line].split(b",")
        cells[value % len(cells)] = [b"nan", b"inf", b"-1e308", b"1e999"][value % 4]
        lines[line] = b",".join(cells)
    elif kind == "gzip":
        return gzip.compress(data)
    return b"\n".join(lines)


def _mutated(mutations: list[tuple[str, int, int]]) -> bytes:
    """The valid file with ``mutations`` (kind, position, value) applied in turn."""
    data = VALID
    for kind, position, value in mutations:
        data = _mutate(data, kind, position, value)
    return data


MUTATIONS = [
    "add_field",
    "drop_field",
    "empty_line",
    "huge_field",
    "huge_extra_field",
    "crlf",
    "cr",
    "mixed_endings",
    "bom",
    "bom_in_line",
    "utf16",
    "latin1",
    "nul",
    "byte",
    "cut",
    "reorder",
    "duplicate_column",
    "duplicate_line",
    "swap_lines",
    "retime",
    "quote",
    "nan",
    "gzip",
]

mutation = st.tuples(
    st.sampled_from([m for m in MUTATIONS if m != "gzip"]),
    st.integers(0, 10_000),
    st.integers(0, 1_000),
)


@FUZZ
@given(mutations=st.lists(mutation, min_size=1, max_size=4), compress=st.booleans())
@example(mutations=[("huge_extra_field", 0, 0)], compress=False)
@example(mutations=[("cr", 0, 0)], compress=False)
@example(mutations=[("bom", 0, 0), ("crlf", 0, 0)], compress=True)
def test_log_reader_on_mutated_valid_files(
    mutations: list[tuple[str, int, int]], compress: bool
) -> None:
    TRIED["log reader, mutated valid files"] += 1
    data = _mutated(mutations)
    if compress:
        data = gzip.compress(data)
    check_log(data)


_CELL = st.one_of(
    st.sampled_from(["", " ", "nan", "-inf", "1e309", "0x10", "1_0", "+5", "2024-03-01T06:00:05Z"]),
    st.from_regex(r"-?[0-9]{1,4}(\.[0-9]{0,3})?", fullmatch=True),
    st.text(max_size=8),
)
_STAMP = st.one_of(
    st.integers(-5, 200_000).map(
        lambda s: (T0_UTC + dt.timedelta(seconds=s)).strftime(lf.TIME_FORMAT)
    ),
    st.text(max_size=25),
)


@FUZZ
@given(
    rows=st.lists(
        st.tuples(
            _STAMP,
            st.one_of(st.lists(_CELL, min_size=8, max_size=8), st.lists(_CELL, max_size=12)),
        ),
        max_size=30,
    ),
    ending=st.sampled_from(["\n", "\r\n"]),
    last_newline=st.booleans(),
    header=st.one_of(
        st.just(list(lf.COLUMNS)),
        st.permutations(lf.COLUMNS),
        st.lists(
            st.sampled_from([*lf.COLUMNS, "extra", " time_utc ", "Speed_kmh", ""]), max_size=12
        ),
    ),
)
@example(rows=[("2024-03-01T06:00:01Z", ["1"] * 8)], ending="\n", last_newline=True, header=[])
def test_log_reader_on_generated_rows(
    rows: list[tuple[str, list[str]]], ending: str, last_newline: bool, header: list[str]
) -> None:
    """Rows of generated cells under a header of the log's columns in any order, some left
    out, unknown or repeated; the time cell is in the header's time column."""
    TRIED["log reader, generated rows"] += 1
    at = header.index("time_utc") if "time_utc" in header else 0
    lines = [",".join(header)] + [
        ",".join([*cells[:at], stamp, *cells[at:]]) for stamp, cells in rows
    ]
    text = ending.join(lines) + (ending if last_newline else "")
    check_log(text.encode("utf-8", "surrogatepass"))


@FUZZ
@given(body=st.binary(max_size=2_000), header=st.booleans())
@example(body=b"\x00\x00\x00\n", header=True)
@example(body=b"\r\r\n\n", header=True)
@example(body=b"\x1f\x8b", header=False)
def test_log_reader_on_arbitrary_bytes(body: bytes, header: bool) -> None:
    TRIED["log reader, arbitrary bytes"] += 1
    data = (",".join(lf.COLUMNS).encode() + b"\n" + body) if header else body
    check_log(data)


@FUZZ
@given(mutations=st.lists(mutation, min_size=1, max_size=3), gz_name=st.booleans())
def test_worker_preparation_quarantines_only_with_a_reason(
    mutations: list[tuple[str, int, int]], gz_name: bool
) -> None:
    """The per-file work of an ingestion worker: read, hash, judge; never a reader failure."""
    TRIED["worker preparation"] += 1
    data = _mutated(mutations)
    relpath = lf.log_relpath(WAGON, T0_UTC, gzip=gz_name).as_posix()
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder, relpath)
        path.parent.mkdir(parents=True)
        path.write_bytes(data)
        entry = LogEntry(relpath, path, len(data), 0)
        (prepared,) = prepare_partition(FilePartition((entry,), {WAGON: None}), CONFIG)
    assert prepared is not None and prepared.wagon_id == WAGON
    if prepared.quarantine is not None:
        assert prepared.quarantine.code in QUARANTINE_CODES, prepared.quarantine.reason
        assert prepared.quarantine.reason.startswith(f"{relpath}: ")
    if prepared.parsed is not None:
        repairs = prepared.parsed.repairs
        assert prepared.parsed.frame.height + repairs.rows_rejected == _data_lines(data)
        if prepared.quarantine is not None:  # every row rejected
            assert prepared.quarantine.code == "rows" and not prepared.parsed.frame.height


# --------------------------------------------------------------------------------------------
# The registry reader


def check_registry(content: bytes) -> set[str | None] | None:
    """Load ``content`` as a ``fleet.toml`` and assert the invariant; None if it is refused,
    else the ids loaded or named in a problem."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder, "fleet.toml")
        path.write_bytes(content)
        try:
            registry = load_registry(path)
        except RegistryError as error:
            assert str(error).startswith(f"{path}: "), str(error)
            OUTCOMES["registry reader outcome: refused (RegistryError)"] += 1
            return None
    for problem in registry.problems:
        assert str(problem).startswith(str(path)), str(problem)
    named = {p.wagon_id for p in registry.problems}
    for wagon_id, config in registry.wagons.items():
        assert config.wagon_id == wagon_id and wagon_id not in named
        assert registry.wagon(wagon_id) is config
    for wagon_id in named - {None}:
        assert wagon_id not in registry.wagons
    registry.check_held([])
    outcome = "loaded, problems named" if registry.problems else "loaded"
    OUTCOMES[f"registry reader outcome: {outcome}"] += 1
    OUTCOMES["registry reader: wagons loaded"] += len(registry.wagons)
    OUTCOMES["registry reader: wagons named in a problem"] += len(named - {None})
    return set(registry.wagons) | named


def _entry_ids(document: dict[str, Any]) -> list[object]:
    wagons = document.get("wagon")
    if not isinstance(wagons, list):
        return []
    return [w.get("id") for w in wagons if isinstance(w, dict)]


def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return '"' + "".join(_toml_char(c) for c in value) + '"'
    if isinstance(value, dt.datetime | dt.date):
        return value.isoformat()
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(type(value))


def _toml_char(char: str) -> str:
    if char.isprintable() and char not in '"\\':
        return char
    return f"\\u{ord(char):04x}" if ord(char) < 0x10000 else f"\\U{ord(char):08x}"


def _toml_key(key: str) -> str:
    return _toml_value(key)


def _toml(document: dict[str, Any]) -> str:
    """``document`` as TOML text: a table per dict value, ``[[wagon]]`` per wagon entry."""
    out = []
    for key, value in document.items():
        if not isinstance(value, dict | list) or (isinstance(value, list) and key != "wagon"):
            out.append(f"{_toml_key(key)} = {_toml_value(value)}")
    for key, value in document.items():
        if isinstance(value, dict):
            out.append(f"[{_toml_key(key)}]")
            out.extend(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items())
        elif key == "wagon" and isinstance(value, list):
            if not value:
                out.insert(0, "wagon = []")
            for entry in value:
                out.append("[[wagon]]")
                out.extend(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in entry.items())
    return "\n".join(out) + "\n"


_SCALAR = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(10**30), 10**30),
    st.integers(-3, 70),
    st.floats(-1.0, 2.0),
    st.booleans(),
    st.text(max_size=10),
    st.sampled_from(["cast-iron-P10", "composite-K", "LL", ""]),
    st.datetimes(min_value=dt.datetime(1, 1, 1), max_value=dt.datetime(9999, 1, 1)),
)
_VALUE = st.one_of(
    _SCALAR,
    st.lists(_SCALAR, max_size=3),
    st.dictionaries(st.text(max_size=4), _SCALAR, max_size=2),
)
_KEY = st.one_of(st.sampled_from(sorted(KEY_RANGES)), st.text(min_size=1, max_size=12))


def _near(key: str) -> st.SearchStrategy[object]:
    """Values of ``key`` in or just outside its range (most of a generated wagon is valid, so
    that the checks between keys are reached)."""
    rule = KEY_RANGES[key]
    if rule.kind == "name":
        return st.sampled_from(["cast-iron-bgu", "cast-iron-bg"])
    low = -0.2 if rule.low is None else rule.low
    high = 0.2 if rule.high is None else rule.high
    if rule.kind == "count":
        return st.integers(int(low) - 1, int(high) + 1)
    return st.one_of(
        st.floats(low, high),
        st.sampled_from([low, high, -low, math.nextafter(high, math.inf)]),
        st.integers(math.floor(low), math.ceil(high)),
    )


_NEAR_KEYS = st.lists(st.sampled_from(sorted(KEY_RANGES)), unique=True, max_size=6).flatmap(
    lambda keys: st.fixed_dictionaries({k: _near(k) for k in keys})
)
_KEYS = st.one_of(_NEAR_KEYS, st.dictionaries(_KEY.filter(lambda k: k != "id"), _VALUE, max_size=5))
_ID = st.one_of(
    st.sampled_from(["SGG-0001", "SGG-0002", "SGG-0003", "", " SGG", "a" * 65]),
    st.text(max_size=10),
    _SCALAR,
)
_WAGON = st.builds(
    lambda wagon_id, keys, with_id: ({"id": wagon_id} if with_id else {}) | keys,
    _ID,
    _KEYS,
    st.integers(0, 9).map(lambda n: n > 0),
)
_DOCUMENT = st.fixed_dictionaries(
    {},
    optional={
        "defaults": st.one_of(_NEAR_KEYS, st.dictionaries(_KEY, _VALUE, max_size=6), _SCALAR),
        "wagon": st.one_of(st.lists(_WAGON, max_size=5), _SCALAR),
        "fleet": _VALUE,
    },
)

_NEAR_DOCUMENT = st.fixed_dictionaries(
    {
        "defaults": _NEAR_KEYS,
        "wagon": st.lists(_NEAR_KEYS, max_size=4).map(
            lambda entries: [{"id": f"SGG-{i:04d}"} | keys for i, keys in enumerate(entries)]
        ),
    }
)
"""A registry of well-formed ids whose values lie in or just outside their ranges."""


@FUZZ
@given(document=st.one_of(_DOCUMENT, _NEAR_DOCUMENT))
@example(document={"defaults": {"wheel_radius_m": 10**400}})
@example(document={"wagon": [{"id": "SGG-0001", "blocks_per_bogie": 10**400}]})
def test_registry_reader_on_generated_documents(document: dict[str, Any]) -> None:
    TRIED["registry reader, generated documents"] += 1
    text = _toml(document)
    assert _toml(tomllib.loads(text)) == text  # the generator writes the document it means
    wagons = check_registry(text.encode())
    if wagons is None:
        return
    for wagon_id in _entry_ids(document):  # every entry with an id: loaded, or named
        if isinstance(wagon_id, str):
            assert wagon_id in wagons, wagon_id


_VALID_REGISTRY = registry_text(
    ["SGG-0001", "SGG-0002"], '[[wagon]]\nid = "SGG-0003"\ncylinder_diameter_m = 0.3\n'
).encode()


@FUZZ
@given(
    mutations=st.lists(
        st.tuples(
            st.sampled_from(["byte", "nul", "cut", "crlf", "bom", "insert"]),
            st.integers(0, 10_000),
            st.binary(min_size=1, max_size=12),
        ),
        min_size=1,
        max_size=4,
    )
)
@example(mutations=[("insert", 0, b"a = " + b"[" * 3000 + b"]" * 3000 + b"\n")])
@example(mutations=[("insert", 0, b"x = 1" + b"0" * 5000 + b"\n")])
def test_registry_reader_on_mutated_valid_files(mutations: list[tuple[str, int, bytes]]) -> None:
    TRIED["registry reader, mutated valid files"] += 1
    data = _VALID_REGISTRY
    for kind, position, payload in mutations:
        at = position % (len(data) + 1)
        if kind == "byte":
            data = data[:at] + payload[:1] + data[at + 1 :]
        elif kind == "nul":
            data = data[:at] + b"\x00" + data[at:]
        elif kind == "cut":
            data = data[:at]
        elif kind == "crlf":
            data = data.replace(b"\n", b"\r\n")
        elif kind == "bom":
            data = b"\xef\xbb\xbf" + data
        else:
            data = data[:at] + payload + data[at:]
    check_registry(data)


@FUZZ
@given(
    content=st.one_of(
        st.binary(max_size=500),
        st.text(max_size=300).map(lambda t: t.encode("utf-8", "surrogatepass")),
    )
)
def test_registry_reader_on_arbitrary_bytes(content: bytes) -> None:
    TRIED["registry reader, arbitrary bytes"] += 1
    check_registry(content)


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        (b"[defaults]\nwheel_radius_m = 1" + b"0" * 400 + b"\n", "must be a number in [0.3, 0.65]"),
        (b'[[wagon]]\nid = "A"\nblocks_per_bogie = 1' + b"0" * 400 + b"\n", "must be an integer"),
        (b"a = " + b"[" * 5000 + b"]" * 5000 + b"\n", "nested too deeply"),
        (b"a = " + b"{b = " * 3000 + b"1" + b"}" * 3000 + b"\n", "nested too deeply"),
        (b"a = 1" + b"0" * 5000 + b"\n", "not a usable TOML file"),
    ],
    ids=["huge-number", "huge-count", "deep-arrays", "deep-tables", "too-many-digits"],
)
def test_registry_values_too_large_and_nesting_too_deep_are_named(
    tmp_path: Path, content: bytes, expected: str
) -> None:
    path = tmp_path / "fleet.toml"
    path.write_bytes(content)
    try:
        registry = load_registry(path)
    except RegistryError as error:
        assert str(error).startswith(f"{path}: ") and expected in str(error)
        return
    assert not registry.wagons
    assert expected in str(registry.problems[0])


_PER_FILE_SQL = """
WITH named AS (SELECT file_id, sum(rows) AS n FROM file_rejections GROUP BY file_id),
     stored AS (SELECT file_id, count(*) AS n FROM samples GROUP BY file_id)
SELECT path, status, quarantine_code, rows, rows_in_file, rows_rejected,
       coalesce(named.n, 0), coalesce(stored.n, 0)
FROM files LEFT JOIN named USING (file_id) LEFT JOIN stored USING (file_id)
"""
"""Each file of the ledger: path, status, code, rows, rows read, rows rejected, rejected rows
named in ``file_rejections``, samples stored."""


@settings(FUZZ, max_examples=max(1, FUZZ.max_examples // 25))
@given(files=st.lists(st.lists(mutation, min_size=1, max_size=3), min_size=1, max_size=3))
def test_ingestion_stores_or_names_every_row_of_mutated_files(
    files: list[list[tuple[str, int, int]]],
) -> None:
    """Mutated files ingested into a warehouse: each file's rows read are its samples plus its
    rejected rows, every rejected row in ``file_rejections``; a reader failure never."""
    TRIED["ingestion, mutated files"] += 1
    with tempfile.TemporaryDirectory() as folder:
        fleet, db = Path(folder, "fleet"), Path(folder, "fleet.duckdb")
        write_registry(fleet, [WAGON])
        for hour, mutations in enumerate(files):
            relpath = lf.log_relpath(WAGON, T0_UTC + dt.timedelta(hours=hour), gzip=False)
            data = _mutated(mutations).replace(
                b"2024-03-01T06", f"2024-03-01T{6 + hour:02d}".encode()
            )
            (fleet / relpath).parent.mkdir(parents=True, exist_ok=True)
            (fleet / relpath).write_bytes(data)
        run_ingest(fleet, db, config=CONFIG, progress=False)
        with duckdb.connect(str(db), read_only=True) as con:
            rows = con.execute(_PER_FILE_SQL).fetchall()
        assert len(rows) == len(files)
        for path, status, code, stored, read, rejected, named, samples in rows:
            OUTCOMES[f"ingestion outcome: {status}" + (f" ({code})" if code else "")] += 1
            assert code != "error", path
            if read is None:  # quarantined before its rows were read
                assert status == "quarantined" and stored == 0 and samples == 0
                continue
            assert read == _data_lines((fleet / path).read_bytes()), path
            assert stored == samples and read == stored + rejected and named == rejected, path
