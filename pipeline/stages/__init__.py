"""The per-card stages workers run, one module per stage, in flow order.

* :mod:`.filter` - split the card at its gutter and route it by SIFT good-match fraction;
* :mod:`.orientation` - which way up, positive or negative, which eye, and the photo area;
* :mod:`.rectify` - apply the decided orientation, align the crops, rectify the pair;
* :mod:`.disparity` - dense disparity, depth up to scale, the 512 x 512 release maps;
* :mod:`.grade` - the quality grade from the rectified views and disparity maps;
* :mod:`.views` - the five GD images, their cameras and a parallax preview.

Each stage module holds its task (reads its inputs from files, calls the pure functions of its
concept, writes its artifacts), the builder of its inputs from a card's earlier results, and its
declaration (``STAGE``): the driver's catalogue is every module here that has one
(:func:`.spec.declared_stages`). :mod:`.base` holds the one wrapper the tasks share (timing,
parameter hash, typed error to failed record), :mod:`.spec` the declaration type. Nothing here
imports torch at import time: a worker loads the heavy libraries only in the task that needs them.
"""
