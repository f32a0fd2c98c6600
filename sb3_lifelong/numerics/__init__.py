"""
The arithmetic of the updates, apart from what they compute: scoring many actions per state in one critic call and its
bf16 copy (``scoring``), elementwise operations torch runs slowly on a CPU (``fast_ops``), loss computations compiled
with ``torch.compile`` and checked against eager (``compiling``), and what this machine multiplies fast (``hardware``).
"""
