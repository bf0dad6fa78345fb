"""Vehicle simulator bundled with virtsensor (tyre model, vehicle model, CAN signal synthesis)."""
