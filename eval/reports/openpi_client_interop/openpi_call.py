"""openpi's side (its own venv, numpy < 2): openpi_client calls our reference server."""

import sys

import numpy as np
import openpi_client
from openpi_client import msgpack_numpy
from openpi_client.websocket_client_policy import WebsocketClientPolicy

print("openpi_client", openpi_client.__file__, "numpy", np.__version__)
request = msgpack_numpy.unpackb(open("/tmp/agnostos_request.msgpack", "rb").read())
policy = WebsocketClientPolicy(host="localhost", port=int(sys.argv[1]))
print("server metadata:", policy.get_server_metadata())
for step in range(3):
    answer = policy.infer(request)
    print(f"infer #{step}: actions {answer['actions'].dtype} {answer['actions'].shape}:",
          answer["actions"])
    request["sim_state"]["key_actions"] = step + 1  # the episode goes on: next key action
