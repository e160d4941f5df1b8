"""Matcher: the tracking front end per robot, and scan matching on request."""
