"""Helpers the tests and the benchmarks share (after ``numpy.testing``), imported by
no library module (``tests/test_layout.py``).

* :mod:`~.can_peers` -- independent peers of the CAN bridge: cantools encodes and
  decodes from the shipped DBC, ``autosar-e2e`` computes and checks every CRC,
  python-can plays the SLCAN host;
* :mod:`~.can_fault_peers` -- fault-injecting peers: a socketcand server that
  stalls, dies and comes back, a scripted SLCAN serial adapter, a raw SLCAN host;
* :mod:`~.can_rx_burst` -- a sender that bursts sensor frames faster than their
  cycle (the receive side's pace rule).

They need the ``runtime`` (or ``test``, ``bench``) extra and the ``can_bridge``
extension; nothing is imported until a helper module is.
"""
