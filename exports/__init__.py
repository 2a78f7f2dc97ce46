"""Dataset releases: versioned, verifiable exports of the curator-accepted cards.

``exports.release.publish_release`` plans, writes and records a release (``keystone export``);
``exports.verify.verify_release`` checks one (``keystone verify``). Each format is one module of
``exports.formats`` (its writer, README and CHANGELOG lines, Croissant record sets, checks), registered
by itself; writers know nothing of the database; ``exports.catalogue`` streams cards to them.
"""
