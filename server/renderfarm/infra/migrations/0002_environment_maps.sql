-- Environment maps (.hdr, .exr) are stored beside scenes, content-addressed the same way.
ALTER TABLE scenes DROP CONSTRAINT scenes_format_check;
ALTER TABLE scenes ADD CONSTRAINT scenes_format_check
    CHECK (format IN ('glb', 'gltf', 'hdr', 'exr'));
