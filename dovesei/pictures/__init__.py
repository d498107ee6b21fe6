"""Every picture the project draws, in one place: world and perception previews, trajectory and
bench plots, episode videos. Tools and reports import from here; services never do.
"""
