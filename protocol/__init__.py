"""What every Convoy process agrees on: the wire schema, Zenoh key expressions and sessions, inboxes, exit codes and
process reports. No env code (the job config lives in ``convoy.config``), so the API and actors' wire stay light.
"""
