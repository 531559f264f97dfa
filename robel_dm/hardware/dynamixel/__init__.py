"""Talking to Dynamixel X-series servos over Protocol 2.0.

`client` (DynamixelClient: bulk reads and writes on a serial bus), `protocol`
(packets and their CRC), `control_table` (register addresses and units),
`register_access` (checked single-register reads and writes), `port` (the
serial port, opened exclusively) and `errors`.
"""
