import socket

print(socket.getaddrinfo("pypi.org", 443))
