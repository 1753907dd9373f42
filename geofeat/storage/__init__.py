"""What geofeat keeps on disk and how: atomic writes (`files`), the checked entry folder of the
stores (`entry_folder`), folders of configuration + weights (`pretrained`), JSON settings
(`jsonconfig`), safe loading of PyTorch files (`safe_load`), the bounded in-memory cache
(`lru`), byte sizes (`sizes`) and the cache folder (`cache_folder`).
"""
