"""The demo: mock autopilot + companion service + a Zenoh peer, flying the paper's scenarios.

A client of the service, not part of it: it talks to the companion over Zenoh only, and uses
nothing of the companion but its configuration (`companion.config`).

    python -m demo [--quick] [--autopilot px4|ardupilot] [--out DIR]
"""
