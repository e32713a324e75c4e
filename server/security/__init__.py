"""Who may do what, and how much: tokens and roles, request rates and body sizes, session costs.

* :mod:`server.security.auth` — bearer tokens, roles, and which token sees which session
* :mod:`server.security.limits` — per-session request buckets, the body-size guard, the origin check
* :mod:`server.security.quotas` — what a session's config may cost: safe ranges, memory per session and token
"""
