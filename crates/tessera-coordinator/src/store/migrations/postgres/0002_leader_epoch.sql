-- The fencing epoch of high availability (docs/store.md, "High availability"): raised by
-- each coordinator that becomes the active one, checked by every state-changing write of
-- a coordinator, so a coordinator that lost the leadership cannot write any more.
INSERT INTO counters (name, value) VALUES ('leader_epoch', 0);
