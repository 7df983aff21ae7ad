"""openpi's websocket policy protocol on our server: ``wire`` (strict msgpack-numpy), ``keymap``
(openpi observation keys to the policy's features), ``endpoint`` (the websocket server, each
connection a robot of the fleet)."""
