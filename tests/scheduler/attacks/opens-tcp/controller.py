import json
import socket
from pathlib import Path

# The test writes where its host-side servers listen (loopback and the host's address).
for host, port in json.loads(Path("target.json").read_text()):
    socket.create_connection((host, port), timeout=5)
    print(f"connected to {host}:{port}: the sandbox let a TCP connection out")
