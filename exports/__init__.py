"""Dataset releases: versioned, verifiable exports of the curator-accepted cards.

``exports.release.publish_release`` plans, writes and records a release (``keystone export``);
``exports.verify.verify_release`` checks one (``keystone verify``). Writers per format live in
``exports.writers`` and know nothing of the database; ``exports.catalogue`` streams cards to them.
"""
