"""``lacuna view``: a live web page of every stream the daemon fills (issue 20, part 3).

The view is its own process: it subscribes to the daemon's PUB output (or plays a recording),
keeps the newest frame of each stream, computes joint positions with ``mocap.fk`` at the page's
rate and sends them to the browser over Server-Sent Events.  The page (``view/static``) only
draws.  Nothing is fetched from the network: the page, its script and its style ship here.
"""

# the page draws at most PAGE_FPS frames a second (only when a new one came), on a canvas of at
# most PAGE_MAX_DPR device pixels per CSS pixel (a 2x screen rasters 4x the pixels)
PAGE_FPS, PAGE_MAX_DPR = 30.0, 1.0
