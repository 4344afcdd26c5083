"""``lacuna view``: a live web page of every stream the daemon fills (issue 20, part 3).

The view is its own process: it subscribes to the daemon's PUB output (or plays a recording),
keeps the newest frame of each stream, computes joint positions with ``mocap.fk`` at the page's
rate and sends them to the browser over Server-Sent Events.  The page (``view/static``) only
draws.  Nothing is fetched from the network: the page, its script and its style ship here.
"""
