"""The companion's edges: Zenoh and MAVLink adapters, and the wire formats in and out.

`messages` turns inbound bytes into validated, typed NED messages and is the only place a
wire error (`MessageError`) is raised; `encode` writes what goes out.
"""
