"""Recording I/O: what the project writes and reads as data.

* :mod:`virtsensor.recordings.simulated`: a simulated run as the canonical 20 Hz
  table and as a file (CSV table or CAN log).
* :mod:`virtsensor.recordings.manifest`: a campaign directory's manifest (each
  run's rows and sha256) and its in-progress marker.
* :mod:`virtsensor.recordings.files`: which files of a path are recordings, and
  reading one into a table whatever its format.
* :mod:`virtsensor.recordings.check`: the one input check every command that
  reads recordings applies (rate, time order, catalogue ranges, targets).
* :mod:`virtsensor.recordings.mdf`: MDF4 files sampled on the 20 Hz ticks.

The low-level CAN log and CSV codecs are :mod:`virtsensor.recordings.canlog`.
"""
