"""The kernel every feature imports: configuration, the database and its shared models, staff
accounts, request limits and security, audit, and the hooks through which features tell the run
driver what it needs from them. It imports no feature, no driver and no web-app composition."""
