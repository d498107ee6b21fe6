"""Onboard camera service: frames from a real camera, tagged with the vehicle state received over Zenoh."""
