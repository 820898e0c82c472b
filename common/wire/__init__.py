"""Every message the roles exchange, and its one msgpack encoding, in the modules named for each part.

errors (WireError, with the kind of fault), frames (FrameStack: image frames as zstd blobs), codecs (the
codec of each kind of field, and the Message base), messages (the message types), metrics (the learner's and
the actors' figures, typed, and their older untyped form read into them), weights_encoding (how
weights travel compact), envelope (encode and decode: the msgpack envelope), run_shape (does a decoded
message fit the run?). Refused input is counted by common/rejections.py.
"""
