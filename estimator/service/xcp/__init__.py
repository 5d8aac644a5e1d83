"""An ASAM XCP 1.x slave on Ethernet (UDP) for the daemon: measurements on an event per injection and
at 10 Hz, characteristics on a working and a reference page, and the A2L that describes them.

Rooms: :mod:`.protocol` (the wire: codes, errors, the Ethernet header), :mod:`.memory` (the address
space: what each address holds, its A2L description, the calibration pages), :mod:`.a2l` (the A2L
file, written from the memory map), :mod:`.slave` (the UDP server, the commands, DAQ).
"""
