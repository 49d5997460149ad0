#!/usr/bin/env python3
"""Generates the 360 template answers of answers.jsonl (ids a-0000 ... a-0359, all "train").

Deterministic (fixed seed, standard library only): re-running it gives byte-identical lines, and
`check_answers.py` verifies that the template lines of answers.jsonl are exactly this output.

The text comes from phrase templates; the labels are NOT the scenario the generator drew but what
the text says, by GUIDELINES.md (`guideline_labels` below): hedged actions ("possibly brake",
"be ready to stop", "the driver may need to ...") are negative, negated mentions are negative,
scene facts implied by the text count ("the light is red" is a traffic light ahead, "yield to cars
already in the roundabout" is a junction ahead), and explicit slowing for the weather is both
`brake` and `adjust_speed_due_to_weather`.

Why templates are not enough: a matcher tuned on one generator's phrasing learns that generator.
These answers are the train split's bulk; the hand-written answers (source "handwritten") add the
styles real VLMs write, and the whole test split is hand-written.

Usage: python3 gen_answers.py   (prints the template lines; see check_answers.py)
"""
import json
import re
import random
import sys

SEED = 20261122
N = 360

R = random.Random(SEED)


def pick(xs):
    return R.choice(xs)


# ---------------------------------------------------------------------------------------------
# Scene phrases. Each is a full clause.
SETTINGS = [
    "The ego vehicle is travelling on a {adj} urban street",
    "We are driving along a {adj} city road",
    "The car is moving down a {adj} residential street lined with parked cars",
    "The vehicle is cruising on a {adj} multi-lane highway",
    "The clip shows a {adj} two-lane rural road",
    "The dashcam view shows a {adj} downtown avenue with shops on both sides",
    "The ego car is on a {adj} suburban road",
    "Footage shows the vehicle on a {adj} arterial road",
    "The camera faces a {adj} boulevard with a painted median",
    "The scene is a {adj} commercial district street",
    "The car is driving through a {adj} industrial area",
    "The video shows a {adj} one-way street",
]
ADJ = ["busy", "quiet", "wide", "narrow", "moderately busy", "congested", "empty", "tree-lined",
       "well-lit", "dim", "crowded", "calm"]
TIME = ["", "", "", " during the day", " at night", " at dusk", " in the early morning",
        " in the afternoon"]

SCENE_POS = {
    "traffic_light_ahead": [
        "a traffic light is visible ahead", "there is a traffic signal at the next corner",
        "the signal ahead is showing red", "a set of traffic lights is coming up",
        "the light in front has just turned amber", "an overhead signal is ahead of us",
        "traffic signals control the upcoming crossing", "the stoplight ahead is green",
        "a red light is visible a short distance ahead", "there are signal lights hanging over the road ahead",
    ],
    "junction_ahead": [
        "an intersection is approaching", "there is a junction ahead",
        "the road meets a crossroads in about fifty metres", "a T-junction is coming up",
        "a side street joins from the right ahead", "we are nearing a four-way intersection",
        "the road splits at a fork ahead", "a crossing road is visible just ahead",
        "there is a junction with a minor road coming up", "the street ends at an intersection",
    ],
    "pedestrian_crossing_ahead": [
        "a zebra crossing is marked on the road ahead", "there is a crosswalk just ahead",
        "pedestrians are waiting at a crossing ahead", "a pedestrian crossing is coming up",
        "people are walking across the street at the crosswalk", "a marked crosswalk lies ahead",
        "white stripes of a pedestrian crossing are visible ahead",
        "a school crossing with a crossing guard is ahead", "a woman is stepping onto the zebra crossing",
        "a few pedestrians are crossing in front of the car",
    ],
}
SCENE_NEG = {
    "traffic_light_ahead": [
        "there is no traffic light", "no traffic signals are visible", "no signals control this stretch of road",
        "there are no traffic lights in view", "I cannot see any traffic light",
        "there is no signal at this spot",
    ],
    "junction_ahead": [
        "there is no intersection nearby", "no junctions are visible ahead",
        "the road continues straight with no side streets", "there are no crossroads in sight",
    ],
    "pedestrian_crossing_ahead": [
        "no pedestrians are visible", "there are no pedestrians or crosswalks",
        "there is no crosswalk in view", "nobody is crossing the road",
        "no one is on the sidewalk near the road", "there is no pedestrian crossing ahead",
    ],
}
WEATHER_BAD = [
    "it is raining heavily", "the road surface is wet from rain", "dense fog limits visibility",
    "snow is covering the road edges", "the road looks icy", "there is light drizzle and the asphalt is slick",
    "a heavy downpour is reducing visibility", "sleet is falling", "patches of black ice may be present",
    "it is snowing steadily",
]
WEATHER_OK = [
    "the weather is clear", "the road is dry", "visibility is good", "it is sunny",
    "the sky is overcast but the road is dry", "",
]
EXTRA_SCENE = [
    "a bus is parked at a stop on the right", "several cars are queued in the adjacent lane",
    "a cyclist is riding along the bike lane", "trees line both sides of the road",
    "a delivery van is double-parked further up", "the lane markings are clearly visible",
    "a truck is travelling ahead of us", "there are buildings on both sides",
    "street lamps illuminate the road", "a motorcycle is filtering between lanes",
]

# ---------------------------------------------------------------------------------------------
# Manoeuvre phrases (ego actions). {h} is replaced by an optional hedge.
ACT_POS = {
    "turn_left": [
        "{h}turn left at the intersection", "{h}make a left turn", "{h}take the next left",
        "{h}steer left onto the side road", "{h}go left at the junction", "{h}perform a left turn",
        "{h}take the left turn toward the car park", "{h}swing left into the next street",
        "{h}turn to the left", "{h}make a left onto the cross street",
    ],
    "turn_right": [
        "{h}turn right at the intersection", "{h}make a right turn", "{h}take the next right",
        "{h}steer right onto the side road", "{h}go right at the junction", "{h}perform a right turn",
        "{h}take the right turn toward the petrol station", "{h}swing right into the next street",
        "{h}turn to the right", "{h}make a right onto the cross street",
    ],
    "brake": [
        "{h}brake", "{h}apply the brakes", "{h}slow down", "{h}decelerate gently",
        "{h}press the brake pedal", "{h}ease off and brake smoothly", "{h}reduce speed by braking",
        "{h}brake firmly", "{h}start braking now", "{h}bring the speed down with the brakes",
    ],
    "accelerate": [
        "{h}accelerate", "{h}speed up", "{h}pick up speed", "{h}increase speed",
        "{h}press the accelerator", "{h}gain speed to match the flow", "{h}step on the gas",
        "{h}accelerate smoothly", "{h}build up speed", "{h}increase your velocity gradually",
    ],
    "stop": [
        "{h}stop", "{h}come to a complete stop", "{h}stop at the stop line", "{h}halt the vehicle",
        "{h}bring the car to a stop", "{h}stop and wait", "{h}come to a full stop before the line",
        "{h}stop behind the white line", "{h}remain stationary", "{h}pull up and stop",
    ],
    "merge": [
        "{h}merge into the left lane", "{h}merge onto the highway", "{h}change lanes to the right",
        "{h}move over into the next lane", "{h}merge with the traffic in the adjacent lane",
        "{h}switch to the left lane", "{h}blend into the main carriageway",
        "{h}merge as the two lanes become one", "{h}shift into the right-hand lane",
        "{h}join the flow of traffic from the on-ramp",
    ],
    "maintain_safe_distance": [
        "{h}keep a safe distance from the car ahead", "{h}maintain a safe following distance",
        "{h}leave enough space to the vehicle in front", "{h}keep a two-second gap",
        "{h}not tailgate the truck ahead", "{h}hang back from the lead vehicle",
        "{h}increase the gap to the vehicle in front", "{h}stay well behind the bus",
        "{h}avoid following too closely", "{h}keep plenty of room ahead",
    ],
    "check_blind_spot": [
        "{h}check the blind spot", "{h}look over your shoulder", "{h}check mirrors and blind spots",
        "{h}do a shoulder check", "{h}glance at the side mirror and blind spot",
        "{h}make sure nothing is in the blind spot", "{h}verify the adjacent lane is clear",
        "{h}check for vehicles hidden beside you", "{h}scan the blind spot before moving over",
        "{h}look behind to the side for cyclists",
    ],
    "adjust_speed_due_to_weather": [
        "{h}reduce speed because of the wet road", "{h}drive slower given the weather",
        "{h}lower your speed for the rain", "{h}slow down due to the poor visibility in the fog",
        "{h}adapt your speed to the slippery conditions", "{h}take it slower on the icy surface",
        "{h}adjust speed for the weather", "{h}drive more cautiously and slowly in the snow",
        "{h}cut your speed because the road is slick", "{h}moderate speed for the conditions",
    ],
    "yield_to_traffic": [
        "{h}yield to oncoming traffic", "{h}give way to vehicles on the main road",
        "{h}let the crossing traffic pass first", "{h}yield to cars already in the roundabout",
        "{h}give priority to the other vehicles", "{h}wait for a gap in traffic",
        "{h}yield the right of way", "{h}let the approaching car go first",
        "{h}give way at the yield sign", "{h}allow the oncoming vehicles to pass",
    ],
    "drive_as_normal": [
        "{h}continue driving as normal", "{h}proceed as usual", "{h}keep going at the current speed",
        "{h}carry on normally", "{h}maintain the current course and speed",
        "{h}drive on without any special action", "{h}continue straight ahead normally",
        "{h}keep driving steadily", "{h}just keep cruising", "{h}carry on in the current lane",
    ],
}
ACT_NEG = {
    "turn_left": ["there is no need to turn left", "do not turn left here", "turning left is not required"],
    "turn_right": ["there is no need to turn right", "do not turn right here", "a right turn is not needed"],
    "brake": ["there is no need to brake", "braking is not necessary", "no braking is required",
              "you do not have to brake"],
    "accelerate": ["do not accelerate", "there is no need to speed up", "avoid speeding up",
                   "it is not necessary to accelerate"],
    "stop": ["there is no need to stop", "do not stop here", "stopping is not required",
             "you don't have to stop"],
    "merge": ["there is no need to change lanes", "do not merge yet", "no lane change is needed"],
    "check_blind_spot": [],
    "maintain_safe_distance": [],
    "adjust_speed_due_to_weather": ["the weather does not require a change of speed",
                                    "there is no need to slow down for the weather"],
    "yield_to_traffic": ["there is no traffic to yield to", "no need to give way"],
    "drive_as_normal": [],
}
HEDGES = ["", "", "", "", "", "possibly ", "probably ", "be ready to ", "consider whether to ",
          "maybe ", "carefully "]
HEDGE_LEAD = ["The vehicle should", "The driver should", "We should", "I recommend that the driver",
              "The ego car needs to", "It would be wise to", "The best action is to", "You should",
              "The car might need to", "The driver may need to", "It is advisable to",
              "The recommended manoeuvre is to"]

# Rationale phrases keyed by label; {x} filled with a scene cue.
RATIONALE = {
    "turn_left": ["the planned route continues to the left", "the destination lies down the street on the left"],
    "turn_right": ["the route requires heading right", "the navigation indicates a right turn"],
    "brake": ["the gap to the vehicle in front is closing", "the car ahead has its brake lights on",
              "the speed is too high for what is coming"],
    "accelerate": ["the road ahead is clear and we are below the limit",
                   "traffic in the target lane is moving faster"],
    "stop": ["the light is red", "a stop sign is posted at the corner", "the way ahead is blocked"],
    "merge": ["the current lane is ending", "the exit is on the other side"],
    "maintain_safe_distance": ["the truck ahead may stop suddenly", "reaction time must be preserved"],
    "check_blind_spot": ["a motorcyclist could be hidden beside the car", "changing lanes without looking is unsafe"],
    "adjust_speed_due_to_weather": ["stopping distances grow on slippery surfaces",
                                    "visibility is reduced by the weather"],
    "yield_to_traffic": ["the other vehicles have priority", "oncoming cars have the right of way"],
    "drive_as_normal": ["nothing unusual is happening", "the road is clear and traffic flows smoothly",
                        "there are no hazards that call for a change"],
    "traffic_light_ahead": ["the signal controls the intersection"],
    "junction_ahead": ["vehicles may enter from the side road"],
    "pedestrian_crossing_ahead": ["pedestrians may step onto the crossing at any moment"],
}
RAT_LEAD = ["This is because", "The reason is that", "Rationale:", "Because", "This is necessary since",
            "The main reason is that", "Given that", "It makes sense since"]

# Coherent scenarios: (scene labels, action label options). Each scenario lists labels that are
# likely together; one answer draws a subset.
SCENARIOS = [
    (["traffic_light_ahead", "junction_ahead"], ["stop", "brake", "turn_left", "turn_right", "yield_to_traffic"]),
    (["traffic_light_ahead"], ["stop", "brake", "accelerate", "drive_as_normal"]),
    (["junction_ahead"], ["turn_left", "turn_right", "yield_to_traffic", "brake", "stop", "check_blind_spot"]),
    (["pedestrian_crossing_ahead"], ["brake", "stop", "yield_to_traffic"]),
    (["pedestrian_crossing_ahead", "traffic_light_ahead"], ["stop", "brake"]),
    ([], ["merge", "check_blind_spot", "accelerate", "maintain_safe_distance"]),
    ([], ["maintain_safe_distance", "brake", "adjust_speed_due_to_weather"]),
    ([], ["drive_as_normal", "maintain_safe_distance"]),
    ([], ["drive_as_normal"]),
    (["junction_ahead"], ["turn_left", "check_blind_spot", "yield_to_traffic"]),
    (["junction_ahead", "pedestrian_crossing_ahead"], ["turn_right", "yield_to_traffic", "brake"]),
]

EXCLUSIVE_NORMAL = {"turn_left", "turn_right", "brake", "stop", "merge", "adjust_speed_due_to_weather",
                    "yield_to_traffic", "accelerate", "check_blind_spot"}


LAYOUTS = ["three_step", "markdown_three_part", "step_inline", "numbered_paren", "key_value"]

# ---------------------------------------------------------------------------------------------
# Labelling by GUIDELINES.md. The generator's scenario ("intent") labels are not the answer's
# labels: the text decides. These tables encode the guideline rules that the template phrases
# touch; the CHANGES section of GUIDELINES.md lists what they changed.

# Hedges (GUIDELINES "Hedges"): an uncertainty adverb or a "be ready to" makes the action a
# possibility, not a recommendation. "consider whether to" and "carefully" are not hedges.
HEDGE_WORDS = {"possibly ", "probably ", "be ready to ", "maybe "}
# A modal of possibility in the lead scopes over every manoeuvre listed after it.
HEDGE_LEADS = {"The car might need to", "The driver may need to"}
# Weather phrases with explicit slowing language also give `brake` (GUIDELINES "brake").
WEATHER_SLOWING = {
    "reduce speed because of the wet road", "drive slower given the weather",
    "lower your speed for the rain", "slow down due to the poor visibility in the fog",
    "take it slower on the icy surface", "drive more cautiously and slowly in the snow",
    "cut your speed because the road is slick",
}
# Manoeuvre phrases that name a junction or a turn onto another road: the junction is a scene
# fact whether or not the manoeuvre itself is hedged (GUIDELINES "junction_ahead").
JUNCTION_PHRASES = {
    "turn left at the intersection", "take the next left", "steer left onto the side road",
    "go left at the junction", "swing left into the next street", "make a left onto the cross street",
    "turn right at the intersection", "take the next right", "steer right onto the side road",
    "go right at the junction", "swing right into the next street", "make a right onto the cross street",
    "yield to cars already in the roundabout",
}
# Scene phrases that do not assert a marked crossing (pedestrians in general).
NOT_A_CROSSING = {"a few pedestrians are crossing in front of the car"}
# Rationale clauses that assert scene facts.
RATIONALE_FACTS = {
    "the light is red": ["traffic_light_ahead"],
    "the signal controls the intersection": ["traffic_light_ahead", "junction_ahead"],
    "vehicles may enter from the side road": ["junction_ahead"],
    "pedestrians may step onto the crossing at any moment": ["pedestrian_crossing_ahead"],
}


# The ontology's order (PAPER-METHOD.md §1); labels are written in this order.
ONTOLOGY = ["turn_left", "turn_right", "brake", "accelerate", "stop", "traffic_light_ahead",
            "junction_ahead", "pedestrian_crossing_ahead", "merge", "maintain_safe_distance",
            "check_blind_spot", "adjust_speed_due_to_weather", "yield_to_traffic", "drive_as_normal"]


def guideline_labels(meta):
    out = set()
    presupposed = set()
    for label, phrase in meta["scene"].items():
        if phrase not in NOT_A_CROSSING:
            out.add(label)
    hedged_lead = meta["lead"] in HEDGE_LEADS
    for label, hedge, phrase in meta["acts"]:
        if phrase in JUNCTION_PHRASES:
            presupposed.add("junction_ahead")
        if hedged_lead or hedge in HEDGE_WORDS:
            continue
        out.add(label)
        # "Reduce speed because of the wet road. There is no need to brake." denies the label's
        # own word: the denial wins (GUIDELINES G8).
        if phrase in WEATHER_SLOWING and meta.get("negated") != "brake":
            out.add("brake")
    for bit in meta["rationale"]:
        presupposed.update(RATIONALE_FACTS.get(bit, []))
    # An explicit denial in the scene description ("there are no crossroads in sight") beats a
    # presupposition of the same element elsewhere (GUIDELINES "Contradictions").
    out.update(presupposed - meta["denied"])
    return sorted(out, key=ONTOLOGY.index)


def cap(s):
    return s[:1].upper() + s[1:] if s else s


def join_list(xs):
    if len(xs) == 1:
        return xs[0]
    return ", ".join(xs[:-1]) + pick([" and ", ", and ", ", then "]) + xs[-1]


def make_answer():
    scene_labels, action_pool = pick(SCENARIOS)
    labels = set()
    # scene labels: each present with high probability
    scene_on = [l for l in scene_labels if R.random() < 0.85]
    # actions: 1-3 from the pool
    k = R.choice([1, 1, 2, 2, 2, 3])
    actions = R.sample(action_pool, min(k, len(action_pool)))
    if "turn_left" in actions and "turn_right" in actions:
        actions.remove("turn_right")
    if "drive_as_normal" in actions:
        actions = [a for a in actions if a not in EXCLUSIVE_NORMAL]
    if "stop" in actions and "accelerate" in actions:
        actions.remove("accelerate")
    bad_weather = R.random() < 0.22
    if bad_weather and R.random() < 0.7 and "drive_as_normal" not in actions:
        actions.append("adjust_speed_due_to_weather")
    if "adjust_speed_due_to_weather" in actions and not bad_weather:
        bad_weather = True
    labels.update(scene_on)
    labels.update(actions)

    # ----- scene -----
    parts = []
    setting = pick(SETTINGS).format(adj=pick(ADJ)) + pick(TIME)
    parts.append(setting)
    meta = {"scene": {}, "acts": [], "lead": None, "rationale": [], "weather_bad": bad_weather}
    for l in scene_on:
        p = pick(SCENE_POS[l])
        meta["scene"][l] = p
        parts.append(p)
    # negated scene mentions of absent scene labels
    absent_scene = [l for l in SCENE_NEG if l not in scene_on]
    R.shuffle(absent_scene)
    meta["denied"] = set()
    for l in absent_scene[: R.choice([0, 0, 1, 1, 2])]:
        meta["denied"].add(l)
        parts.append(pick(SCENE_NEG[l]))
    if bad_weather:
        parts.append(pick(WEATHER_BAD))
    else:
        w = pick(WEATHER_OK)
        if w and R.random() < 0.5:
            parts.append(w)
    if R.random() < 0.6:
        parts.append(pick(EXTRA_SCENE))
    first = parts[0]
    rest = parts[1:]
    R.shuffle(rest)
    if R.random() < 0.5 and rest:
        scene = cap(first) + ". " + ". ".join(cap(p) for p in rest) + "."
    else:
        scene = cap(first) + (", and " if len(rest) == 1 else "; ") + "; ".join(rest) + "." if rest else cap(first) + "."

    # ----- manoeuvre -----
    acts = list(actions)
    R.shuffle(acts)
    phrases = []
    for a in acts:
        h = pick(HEDGES)
        p = pick(ACT_POS[a])
        meta["acts"].append((a, h, p.format(h="")))
        phrases.append(p.format(h=h).strip())
    lead = pick(HEDGE_LEAD)
    meta["lead"] = lead
    man = lead + " " + join_list(phrases) + "."
    # negated actions of absent actions
    neg_candidates = [a for a, v in ACT_NEG.items() if v and a not in labels]
    if R.random() < 0.45 and neg_candidates:
        a = pick(neg_candidates)
        meta["negated"] = a
        man += " " + cap(pick(ACT_NEG[a])) + "."
    if R.random() < 0.25:
        man = pick(["Recommended action: ", "Action: ", "Suggested manoeuvre: ", ""]) + man

    # ----- rationale -----
    rat_keys = [l for l in sorted(labels) if l in RATIONALE]
    R.shuffle(rat_keys)
    rat_bits = [pick(RATIONALE[l]) for l in rat_keys[: R.choice([1, 1, 2])]]
    meta["rationale"] = rat_bits
    rationale = pick(RAT_LEAD) + " " + " and ".join(rat_bits) + "."
    if bad_weather and "adjust_speed_due_to_weather" not in labels:
        # weather mentioned, but the answer says it does not matter
        rationale += " " + pick(["Despite the weather, no change of speed is needed.",
                                 "The rain is light, so there is no need to slow down for it."])
        # the sentence says no slowing for weather: label stays off
    if R.random() < 0.3:
        rationale += " " + pick(["Safety is the priority.", "This keeps the manoeuvre smooth.",
                                 "Other road users should be watched carefully.",
                                 "This follows standard traffic rules."])

    layout = R.randrange(5)
    if layout == 0:
        text = f"1. Scene description: {scene}\n2. Recommended manoeuvres: {man}\n3. Rationale: {rationale}"
    elif layout == 1:
        text = f"**Scene:** {scene}\n**Manoeuvre:** {man}\n**Why:** {rationale}"
    elif layout == 2:
        text = f"Step 1 - Describe the scene: {scene} Step 2 - Manoeuvre: {man} Step 3 - Rationale: {rationale}"
    elif layout == 3:
        text = f"1) {scene}\n2) {man}\n3) {rationale}"
    else:
        text = f"Scene: {scene}\nAction: {man}\nReasoning: {rationale}"
    text = re.sub(r"\b([Aa]) ([aeiou])", r"\1n \2", text)
    meta["layout"] = LAYOUTS[layout]
    return text, guideline_labels(meta), meta


def main():
    out = sys.stdout
    seen = set()
    i = 0
    while i < N:
        text, labels, meta = make_answer()
        if text in seen:
            continue
        seen.add(text)
        rec = {"id": f"a-{i:04d}", "split": "train", "text": text, "labels": labels,
               "source": "template", "style": meta["layout"]}
        out.write(json.dumps(rec, ensure_ascii=False) + "\n")
        i += 1


if __name__ == "__main__":
    main()
