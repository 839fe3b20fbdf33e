"""Settings, database engine/sessions and API-key hashing shared by the API and the workers."""
