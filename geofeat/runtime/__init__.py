"""Where and how geofeat runs: devices (`devices`), ranks under ``torchrun`` (`distributed`),
progress bars (`progress`) and worker processes that end with their parent (`processes`).
"""
