"""Package data: the shipped models, installed as ``virtsensor.assets.models`` (see virtsensor.assets)."""
