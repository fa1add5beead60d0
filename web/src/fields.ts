// Which input of the submit form an API error's field belongs to. The server names a field
// as a path: "settings.width", "settings.frames[2]", "name", and for a USD scene's refusal the
// prim and attribute after "scene:" ("scene:/World/Looks/Wood/Texture.inputs:file",
// "scene:shot.usda.subLayers[0]"): the input is the path's first name, up to the first '.',
// '[' or ':'; for "settings.X" the setting X.

/** The first name of a field path: "scene" for "scene:/World/Tex.inputs:file". */
export const fieldHead = (field: string): string => field.split(/[.[:]/)[0];

/** The setting a "settings.X..." field names ("" for any other field). */
export const fieldSetting = (field: string): string =>
  fieldHead(field) === "settings" ? fieldHead(field.slice("settings.".length)) : "";
