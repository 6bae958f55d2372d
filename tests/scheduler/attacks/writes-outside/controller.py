from pathlib import Path

Path("/code/planted.py").write_text("print('pwned')\n")
