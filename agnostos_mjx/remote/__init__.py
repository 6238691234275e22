"""Policies served in their own process: openpi's websocket protocol (client and server)."""
