"""The CAN layer: the DBC generator (:mod:`.dbcgen`), AUTOSAR E2E Profile 11 (:mod:`.e2e`) and the one codec
(:mod:`.codec`: DBC tables, generated encoders/decoders, :class:`~virtsensor.canbus.codec.CanMatrix`)."""
