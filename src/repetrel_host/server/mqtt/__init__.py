"""MQTT: the bridge that publishes each printer's state and takes commands (:mod:`.bridge`),
and Home Assistant's discovery (:mod:`.homeassistant`)."""
