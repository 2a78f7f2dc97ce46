"""The per-card stage tasks workers run, one module per stage, in flow order.

* :mod:`.filter` - split the card at its gutter and route it by SIFT good-match fraction;
* :mod:`.rectify` - apply the decided orientation, align the crops, rectify the pair;
* :mod:`.disparity` - dense disparity, depth up to scale, the 512 x 512 release maps;
* :mod:`.grade` - the quality grade from the rectified views and disparity maps;
* :mod:`.views` - the five GD images, their cameras and a parallax preview.

Each task reads its inputs from files, calls the pure functions of its concept and writes its
artifacts; :mod:`.base` holds the one wrapper they all share (timing, parameter hash, typed
error to failed record). Modules are imported by name, not from this package, so a worker that
runs the filter never imports torch or the view renderer.
"""
