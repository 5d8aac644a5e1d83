"""Trace CSV reading: the layouts people write by hand or with other tools, and the errors."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.errors import TraceError
from estimator.io.traces import csv_head, read_trace, write_trace

READABLE = {
    "plain": ("# a=1\n# b = 2\nt_s,current_A\n0,1\n1,2\n", {"a": "1", "b": "2"}),
    "CRLF": ("# a=1\r\nt_s,current_A\r\n0,1\r\n1,2\r\n", {"a": "1"}),
    "CR only": ("# a=1\rt_s,current_A\r0,1\r1,2\r", {"a": "1"}),
    "blank lines": ("\n\n# a=1\n\nt_s,current_A\n\n0,1\n\n1,2\n\n", {"a": "1"}),
    "metadata below the header": ("t_s,current_A\n0,1\n# c=5\n1,2\n#a comment\n", {"c": "5"}),
    "spaces": ("  # a=1  \n  t_s , current_A \n 0 , 1 \n1,2   \n", {"a": "1"}),
    "no newline at the end": ("t_s,current_A\n0,1\n1,2", {}),
    "# inside a value": ("# a=x#y\nt_s,current_A\n0,1\n1,2\n", {"a": "x#y"}),
}


@pytest.mark.parametrize("name", READABLE)
def test_trace_layouts_read_to_the_same_columns(tmp_path, name):
    text, meta = READABLE[name]
    p = tmp_path / "t.csv"
    p.write_bytes(text.encode())
    tr = read_trace(p)
    assert list(tr.columns) == ["t_s", "current_A"]
    assert tr.column("t_s").tolist() == [0.0, 1.0] and tr.column("current_A").tolist() == [1.0, 2.0]
    assert tr.meta == meta
    assert csv_head(p)[1].replace(" ", "") == "t_s,current_A"   # the header, whatever the line ends


@pytest.mark.parametrize("text, message", [
    ("# a=1\nt_s,x\n", "has no data rows"),
    ("t_s,x\n# c=1\n\n", "has no data rows"),
    ("", "has no data rows"),
    ("t_s,x\n0,1\n1,abc\n", "unreadable numeric data"),
    ("t_s,x\n0,1\n1,2,3\n", "unreadable numeric data"),
    ("t_s,x,y\n0,1\n1,2\n", "2 columns of data but 3 names"),
])
def test_unreadable_traces_raise_one_readable_line(tmp_path, text, message):
    p = tmp_path / "t.csv"
    p.write_text(text)
    with pytest.raises(TraceError, match=message) as e:
        read_trace(p)
    assert "\n" not in str(e.value)


def test_written_traces_read_back_to_the_bit(tmp_path):
    rng = np.random.default_rng(5)
    cols = {"t_s": np.arange(300) * 0.5e-6, "current_A": rng.normal(size=300), "voltage_V": rng.normal(size=300)}
    p = tmp_path / "t.csv"
    write_trace(p, cols, {"serial": "INJ-1", "time_s": 0.25})
    tr = read_trace(p)
    for k, v in cols.items():
        assert np.array_equal(tr.column(k), np.array([float(f"{x:.10g}") for x in v]))
    assert tr.meta == {"serial": "INJ-1", "time_s": "0.25"}
    assert csv_head(p) == ({"serial": "INJ-1", "time_s": "0.25"}, "t_s,current_A,voltage_V")
