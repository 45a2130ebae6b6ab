"""``bench4d annotate``: a local web app to annotate query masks and time segments.

* :mod:`.session`: the state (one scene, one annotation file, revisions, lock, import/export calls);
* :mod:`.server`: the HTTP front (standard library), with its security model;
* :mod:`.exchange`: import and export, each export reloaded and checked before it replaces a file;
* :mod:`.review`: automatic checks for review mode;
* ``static/``: the page (plain ES modules on a 2D canvas; nothing fetched from elsewhere);
* :mod:`.synthetic`, :mod:`.latency`: test material and the latency/accuracy measurement.
"""
