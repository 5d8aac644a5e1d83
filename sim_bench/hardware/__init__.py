"""The simulated hardware: the injector plant, the amplifiers' drives, series parts and lots, the
node that puts them on a bus, the loopback hub that stands in for SocketCAN, and the process harness
that starts and watches them."""
