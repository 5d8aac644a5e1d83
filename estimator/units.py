"""Unit conversions, one name each: every layer converts through these (a test fails on a bare
``1e6``/``1e-6`` factor anywhere else in the package).

The simulator and the SI fields work in m, s, F, V·s; the search plane, the filter, the bus and the
files in µm and µs (see :mod:`estimator.ident.coords` for the (N_u, L_h) plane). Multiplying by
``M_PER_UM`` is not dividing by ``UM_PER_M`` to the last bit: each conversion keeps the operation it
always had.
"""

from __future__ import annotations

UM_PER_M = 1e6      # µm per m
M_PER_UM = 1e-6     # m per µm
US_PER_S = 1e6      # µs per s
S_PER_US = 1e-6     # s per µs
PER_MICRO = 1e6     # µF per F, µV·s per V·s: the micro prefix of any other unit
MICRO = 1e-6        # F per µF, ...
MEGA = 1e6          # 10^6 N/m per N/m (a stiffness as the tables print it)
