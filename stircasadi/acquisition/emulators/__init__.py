"""Instrument emulators on pseudo-terminals and loopback sockets: links the drivers open like hardware.

When to use: tests, demos and dry runs of ``stircasadi acquire`` without a rig. Each emulator
serves one transport:

* ``transport="pty"``: a pty pair (``os.openpty``); the driver opens the slave path
  (``emulator.port``, e.g. ``/dev/pts/7``) through pyserial exactly as it would open
  ``/dev/ttyUSB0``;
* ``transport="tcp"``: a TCP socket on the loopback address only (127.0.0.1, an ephemeral port);
  ``emulator.port`` is the VISA resource ``TCPIP0::127.0.0.1::<port>::SOCKET`` that the drivers
  open through pyvisa, as they would a LAN instrument.

A thread answers with the wire protocol documented in ``scope``, ``scan`` and ``counter``.

Data come from a pluggable callable ``trace_for(i) -> (n_observed, n_bins)`` (the ideal STIR row
for aimed patch ``i``, e.g. the forward model's ``simulate(scene, grid).stir[i]``), shared through
a :class:`Bench` that also remembers where the scan controller aims:

* the counter returns ``Poisson(shots * (gain * trace + dark))`` counts (or, with
  ``pileup=True``, classic TCSPC first-photon histograms: a multinomial over bins with
  probabilities ``exp(-sum_{j<k} lam_j) (1 - exp(-lam_k))``, ``lam = gain * trace + dark``);
* the oscilloscope returns ``volts_per_unit * trace + N(0, noise_v)`` quantised to 16 bits.

Fault injection (:class:`Fault`, fired on the ``nth`` time a command starting with ``command``
arrives, once unless ``once=False``): ``stall`` (reply after ``stall_s``), ``drop`` (``n_bytes``
removed from the middle of the reply), ``garbage`` (``n_bytes`` of noise before the reply),
``truncate`` (only the first half of the reply is sent), ``badlength`` (a binary block's header
becomes ``#9099999999`` and nothing follows: a corrupt length field), ``disconnect`` (the port
hangs up: the pty or socket is closed, like an unplugged cable; :meth:`EmulatedDevice.reconnect`
plugs it back in on a new path). The scope emulator can also ignore ``DATA:SOURCE``
(``ignores_source=True``: always channel 1, as a misconfigured scope does) and send a DPO-style
preamble with extra fields (``dpo_preamble=True``).

Threads are daemons and :meth:`EmulatedDevice.stop` always joins them (use the emulators as context
managers); writes are non-blocking so a client that stops reading never hangs the emulator.

Neglects: baud-rate timing (a pty moves bytes as fast as it can).
"""
from .base import FAULT_KINDS, TRANSPORTS, Bench, EmulatedDevice, Fault
from .devices import CounterEmulator, EmulatedRig, ScanControllerEmulator, ScopeEmulator

__all__ = ["FAULT_KINDS", "TRANSPORTS", "Bench", "CounterEmulator", "EmulatedDevice", "EmulatedRig",
           "Fault", "ScanControllerEmulator", "ScopeEmulator"]
