"""Acquisition: measured traces in from instruments (pyserial) and files, into a ``Capture``.

Modules
-------
protocol     IEEE-488.2 definite-length blocks, line checks (shared by drivers and emulators)
serialio     ``SerialSettings`` and the binary-safe ``Port`` (deadlines, retries, clear errors)
scope        SCPI oscilloscopes (Tektronix ``WFMOutpre?``/``CURVE?``, LeCroy ``WF?``)
scan         the galvo scan controller (line protocol with acknowledgements)
counter      the histogramming TCSPC counter
emulators    emulators of all three on ptys or loopback sockets, with fault injection
             (base: faults, bench, served device; devices: the instruments and the rig)
session      ``acquire``: patch-by-patch capture into the Capture HDF5 file, flush per trace, resume
importers    ``import_file``: PTU/PHU, y-tal, Zaragoza NLOS, CSV, NPZ, and the .mat readers
calibration  time zero, impulse response, background, pile-up/dead-time correction
cli          the ``import`` and ``acquire`` subcommands
"""
