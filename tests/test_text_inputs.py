"""Text data files (g2o, TORO, TUM, KITTI, relations, stamp lists): any byte gives a project error naming
the file and line, numbers follow the C locale grammar, and a graph's edges use declared vertices."""

from __future__ import annotations

import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.errors import GraphFormatError, InputFileError, LogFormatError
from core.numbers import c_float, c_int
from core.trajectory import read_g2o_vertices, read_kitti, read_tum
from evaluation.relations import read_relations
from slam.graph import read_g2o, read_graph, read_toro

# The decimal strtod grammar of the C locale, written out independently of core.numbers.
from slam.trajectory_io import read_trajectory

# The decimal strtod grammar of the C locale, written out independently of core.numbers.
C_FLOAT = re.compile(r"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|inf|infinity|nan)", re.I)
C_INT = re.compile(r"[+-]?[0-9]+")

GOOD_LINE = {
    "g2o": "VERTEX_SE2 0 0 0 0",
    "toro": "VERTEX2 0 0 0 0",
    "tum": "1.0 0 0 0 0 0 0 1",
    "kitti": "1 0 0 0 0 1 0 0 0 0 1 0",
    "relations": "1.0 2.0 0 0 0 0 0 0",
}
READERS = {
    "g2o": [read_g2o, read_graph],
    "toro": [read_toro, read_graph],
    "tum": [read_tum, read_trajectory],
    "kitti": [read_kitti],
    "relations": [read_relations],
}
CASES = [(fmt, fn) for fmt, fns in READERS.items() for fn in fns] + [("g2o", read_g2o_vertices)]


@pytest.mark.parametrize("fmt,reader", CASES, ids=lambda v: v if isinstance(v, str) else v.__name__)
def test_a_byte_that_is_not_utf8_is_an_error_naming_its_line(tmp_path, fmt, reader):
    """One byte 0x80 on line 2 (a stray byte of a binary file): the reader raises the project error for that
    file at 'line 2' with the byte and its column, never a UnicodeDecodeError."""
    p = tmp_path / f"bad.{fmt}"
    p.write_bytes(GOOD_LINE[fmt].encode() + b"\n1.0 \x80 2\n")
    with pytest.raises(InputFileError) as ei:
        reader(p)
    assert ei.value.path == str(p) and ei.value.where == "line 2"
    assert "0x80" in ei.value.what and "column 5" in ei.value.what


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet=st.sampled_from("0123456789+-.eE_ infatyINFATY\u0663\u06f5\u00b2\uff11x"), max_size=8))
def test_numbers_are_read_by_the_c_grammar(tok):
    """c_float / c_int accept exactly the strings the C locale's strtod / strtol read whole (no '_' digit
    groups, no non-ASCII digits, no surrounding space), with Python's value."""
    if C_FLOAT.fullmatch(tok):
        assert c_float(tok) == float(tok) or c_float(tok) != c_float(tok)  # nan
        assert c_float(tok.encode()) == c_float(tok) or c_float(tok) != c_float(tok)
    else:
        with pytest.raises(ValueError):
            c_float(tok)
    if C_INT.fullmatch(tok):
        assert c_int(tok) == int(tok) == c_int(tok.encode())
    else:
        with pytest.raises(ValueError):
            c_int(tok)


@pytest.mark.parametrize("fmt,line,field", [
    ("g2o", "EDGE_SE2 0 1_000 1 0 0 1 0 0 1 0 1", "1_000"),
    ("g2o", "VERTEX_SE2 \u0663 0 0 0", "\u0663"),
    ("g2o", "VERTEX_SE2 3 0 1_0.5 0", "1_0.5"),
    ("g2o", "VERTEX_SE2 3 0 \u0661.5 0", "\u0661.5"),
    ("toro", "EDGE2 0 1 1 0 0 1 0 1_0 1 0 0", "1_0"),
    ("tum", "1_000.5 0 0 0 0 0 0 1", "1_000.5"),
    ("kitti", "1 0 0 0 0 1 0 0 0 0 1 \u0660", "\u0660"),
    ("relations", "1.0 2.0 0 0 0 0 0 1_0", "1_0"),
])
def test_python_only_numbers_are_refused_with_their_line(tmp_path, fmt, line, field):
    """'1_000' (Python's digit groups) and Arabic-Indic digits are not numbers to the C tools that write
    these files: the reader names the file, the line and the token instead of reading 1000 or 3."""
    p = tmp_path / f"n.{fmt}"
    p.write_text(GOOD_LINE[fmt] + "\n" + line + "\n", encoding="utf-8")
    for reader in READERS[fmt]:
        with pytest.raises(InputFileError) as ei:
            reader(p)
        assert ei.value.where == "line 2" and repr(field) in ei.value.what, ei.value


@pytest.mark.parametrize("reader,text", [
    (read_g2o, "VERTEX_SE2 5 0 0 0\nVERTEX_SE2 6 1 0 0\nEDGE_SE2 5 6 1 0 0 1 0 0 1 0 1\nEDGE_SE2 5 999 1 0 0 1 0 0 1 0 1\n"),
    (read_toro, "VERTEX2 5 0 0 0\nVERTEX2 6 1 0 0\nEDGE2 5 6 1 0 0 1 0 1 1 0 0\nEDGE2 5 999 1 0 0 1 0 1 1 0 0\n"),
])
def test_an_edge_to_an_undeclared_vertex_is_refused(tmp_path, reader, text):
    """A file that declares its vertices cannot add one through an edge: 'EDGE 5 999' names line 4 and
    vertex 999 instead of creating a 999th node without a pose."""
    p = tmp_path / "g.txt"
    p.write_text(text)
    with pytest.raises(GraphFormatError) as ei:
        reader(p)
    assert ei.value.where == "line 4" and "999" in ei.value.what


def test_edges_define_the_nodes_of_a_file_without_vertices(tmp_path):
    """SE-Sync's files have no VERTEX lines: there the edges name the nodes (sorted ids), as before."""
    p = tmp_path / "g.g2o"
    p.write_text("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n")
    g = read_g2o(p)
    assert g.node_ids.tolist() == [0, 1, 2] and not g.has_initial_guess


@pytest.mark.parametrize("reader", [read_g2o, read_tum, read_relations])
def test_a_directory_or_missing_file_is_a_project_error(tmp_path, reader):
    """A folder given as a file, or a name that does not exist: the project error naming it."""
    for p in (tmp_path, tmp_path / "missing.txt"):
        with pytest.raises((LogFormatError, GraphFormatError)) as ei:
            reader(p)
        assert ei.value.path == str(p)
