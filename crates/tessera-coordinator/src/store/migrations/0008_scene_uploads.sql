-- Tessera store, schema version 8: who uploaded each scene and when it was last
-- uploaded, for the scene quotas (the bytes one API token's uploads hold) and the
-- retention of unreferenced scenes (docs/store.md, "Scene storage"). Kept beside
-- `scenes` rather than in it, so the scene rows stay as they were. One row per scene
-- hash: the owner is the first uploader (a scene is stored once, by content), the time
-- the newest upload. A scene without a row (stored before this version) belongs to no
-- token: it counts in the total quota only.

CREATE TABLE scene_uploads (
    hash             TEXT PRIMARY KEY,
    owner            TEXT NOT NULL,
    uploaded_unix_ms INTEGER NOT NULL
) STRICT;

CREATE INDEX scene_uploads_by_owner ON scene_uploads (owner);
