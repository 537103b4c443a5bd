"""The MAVLink edge: dialect, framing, fastcodec (the hot messages' codec), links (sockets, serial), wire types,
signing, the command gate, identity and reports. Everything here but `links` is pure; the flows use the pure parts.
May import: the top-level math, params and errors. Never the flows (command, estimate) or app.
"""
