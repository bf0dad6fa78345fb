"""The real-time virtual-sensor daemon (``virtsensor run``) and its bench (``virtsensor bench``).

Modules:

* :mod:`~virtsensor.daemon.config` -- :class:`RuntimeConfig`, :func:`load_config` (TOML file + overrides);
* :mod:`~virtsensor.daemon.jsonlog` -- JSON-lines logs on stderr (:func:`configure_logging`);
* :mod:`~virtsensor.daemon.layout` -- :class:`InputLayout`: inputs, criticality, messages, health bits and
  outputs, read from the model card and the DBC;
* :mod:`~virtsensor.daemon.validity` -- the VALID/DEGRADED/INVALID/INIT contract as pure functions, and the
  frame-order rules (:class:`FrameOrder`);
* :mod:`~virtsensor.daemon.receive` -- the receive path (generated receivers, drain, clock mapping);
* :mod:`~virtsensor.daemon.publish` -- SAT_FRONT/VS_Health frames and their alive counters;
* :mod:`~virtsensor.daemon.buslink` -- send, bus errors, reconnects;
* :mod:`~virtsensor.daemon.runner` -- threads, signals, shutdown;
* :mod:`~virtsensor.daemon.stats` -- rings of tick timings;
* :mod:`~virtsensor.daemon.sensor` -- :class:`VirtualSensor`, which composes them;
* :mod:`~virtsensor.daemon.bench` -- ``virtsensor bench`` (replays shipped input frames; the simulator only
  for another manoeuvre, the daemon never).
"""

from virtsensor.daemon.config import RuntimeConfig, load_config, read_config_file
from virtsensor.daemon.jsonlog import JsonFormatter, configure_logging, log
from virtsensor.daemon.runner import TICK_NS
from virtsensor.daemon.sensor import STAGES, VirtualSensor
from virtsensor.daemon.validity import DEGRADED, INIT, INVALID, STATUS_NAMES, VALID

__all__ = ["VALID", "DEGRADED", "INVALID", "INIT", "STATUS_NAMES", "TICK_NS", "STAGES", "RuntimeConfig",
           "VirtualSensor", "JsonFormatter", "configure_logging", "load_config", "read_config_file", "log"]
