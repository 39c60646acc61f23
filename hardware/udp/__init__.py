"""The master/slave UDP link: packet layout (protocol), the console's end (link), the slave's end
(server; ``palpation-console slave`` is :mod:`app.slave`), a fault-injecting relay, and the rig builder for real
hardware."""

from hardware.udp.link import UdpLinkSettings, UdpSlaveLink, UdpTactileSensor
from hardware.udp.server import SlaveServer, SlaveServerSettings

__all__ = ["SlaveServer", "SlaveServerSettings", "UdpLinkSettings", "UdpSlaveLink", "UdpTactileSensor"]
