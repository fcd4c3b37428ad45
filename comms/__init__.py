"""The SimPy network model between the robots (thesis 3.3, 7.2).

Imports only the standard library, numpy, simpy and pydantic: never ``sim`` or
``slam``. Modules: ``config`` (the scenario's ``comms:`` section and presets),
``message`` (messages of real bytes), ``loss`` (Bernoulli, Gilbert-Elliott, trace),
``trace`` (CSV link traces), ``link`` (one direction: priority queue, serialization,
propagation), ``availability``
(outages, windows, range, line of sight), ``routing`` (relays), ``accounting``
(tables, metrics, time series), ``network`` (the object the simulator uses), ``load``
(raw-equivalent stereo load), ``bench`` (throughput of the model itself).
"""

from comms.accounting import DropReason, LinkEvent
from comms.config import CommsConfig, KindPolicy, LinkConfig, Preset, resolve_links
from comms.errors import CommsError
from comms.load import StereoStream, raw_stereo_load
from comms.message import Delivery, Message
from comms.network import Network

__all__ = [
    "CommsConfig",
    "CommsError",
    "Delivery",
    "DropReason",
    "KindPolicy",
    "LinkConfig",
    "LinkEvent",
    "Message",
    "Network",
    "Preset",
    "StereoStream",
    "raw_stereo_load",
    "resolve_links",
]
