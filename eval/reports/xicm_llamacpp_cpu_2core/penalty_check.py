"""Reproduction 4: does each penalty field change what llama-cpp-python samples?"""
import json
import sys
import urllib.request

url = sys.argv[1]
base = {"model": "smollm2", "messages": [{"role": "user", "content": "List the numbers one to twenty, in words."}],
        "temperature": 0.1, "top_p": 0.001, "max_tokens": 48, "seed": 0}
for field in ("repetition_penalty", "repeat_penalty"):
    for value in (1.0, 5.0):
        body = json.dumps({**base, field: value}).encode()
        req = urllib.request.Request(url + "/chat/completions", body, {"Content-Type": "application/json"})
        text = json.load(urllib.request.urlopen(req, timeout=300))["choices"][0]["message"]["content"]
        print(f"{field}={value}: {text!r}")
