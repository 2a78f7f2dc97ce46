"""Curator review: the queue, decisions, disputes and gold, the audit trail, grade models, reports.

``review.tasks`` holds the use cases (sync new grades into the queue, decide with optimistic
locking, resolve disputed crowd answers); ``review.views`` the pages; ``review.grading`` stores
and refits the grader's thresholds (the thresholds themselves are pure: ``pipeline.grading``);
``review.report`` the figures of ``keystone report``.
"""
