"""Package data: the CAN matrix, installed as ``virtsensor.assets.dbc`` (see virtsensor.assets)."""
