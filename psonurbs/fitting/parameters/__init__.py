"""First parameters: a (u, v) in [0, 1]^2 for every point, by topology.

An open patch is projected on the plane it faces most squarely (``plane``) or laid flat
from its own neighbourhood graph (``intrinsic``, corrected from coarse to fine), the
choice in ``open_patch``; closed topologies take angles around a fitted axis
(``closed``); ``topology`` builds each topology's net and chooses one by the classical
fit's leave-one-out error.
"""
