"""What every service runs on: the Zenoh session, the service lifecycle, identity, systemd
notification and the bounded inbox."""
